// The headset's XR space registered to the tracker's world (the follower's
// humantele.follower.registration; docs/registration.md).
//
// In AR the page draws in its WebXR 'local-floor' space; the feed's objects are in the
// tracker's world. The follower fits T_world_xr from targets the page shows (XR space) and
// the probe tip the tracker measures on each (world); the page then draws the feed's objects
// under a root placed at T_xr_world. Before a registration exists in AR nothing from the feed
// is drawn and the page says a registration is needed; on a tablet or laptop (no AR) the
// feed's world is drawn as is.
//
// To the follower: {type: 'registration', action: hello|start|take|cancel|reset, headset,
// targets?} and, while registered in AR, {type: 'viewer_pose', headset, position,
// quaternion} a few times a second (the watch). From it: {type: 'registration', headset,
// state: none|collecting|registered|refused|cancelled, message, index, count, refused,
// residual_mm, T_xr_world, watch: waiting|ok|drifted, drift_mm, drift_deg}.

import * as THREE from 'three';

const ID_KEY = 'humantele.headset';
const VIEWER_EVERY_MS = 200; // the viewer pose for the watch: 5 a second
const SHOW_DONE_MS = 5000; // "registered" stays in the banner this long
// Targets in front of the technician at table height: metres right and ahead of the point
// AHEAD in front of the viewer, at the viewer's height minus DROP (within TABLE_Y).
const AHEAD = 0.45;
const DROP = 0.55;
const TABLE_Y = [0.6, 1.2];
// A 36 x 20 cm rectangle: wider targets fix the rotation better (docs/registration.md).
const LAYOUT = [
  [-0.18, -0.1],
  [0.18, -0.1],
  [0.18, 0.1],
  [-0.18, 0.1],
];
const COLOUR = { now: 0x4aa3ff, done: 0x2fbf71, todo: 0xaab4bd };

// This headset's id: random, kept in the browser's storage (one per headset and browser).
function headsetId() {
  try {
    let id = localStorage.getItem(ID_KEY);
    if (!id) {
      const b = crypto.getRandomValues(new Uint8Array(8));
      id = 'h' + [...b].map((x) => x.toString(16).padStart(2, '0')).join('');
      localStorage.setItem(ID_KEY, id);
    }
    return id;
  } catch {
    let h = 0; // no storage: a hash of the browser's user agent
    for (const c of navigator.userAgent) h = (Math.imul(h, 31) + c.charCodeAt(0)) | 0;
    return 'ua' + (h >>> 0).toString(16);
  }
}

const hex = (c) => `#${c.toString(16).padStart(6, '0')}`;
const round5 = (v) => Math.round(v * 1e5) / 1e5; // 0.01 mm: short messages

// A round badge with a number that faces the viewer (width in metres).
function makeBadge(width) {
  const canvas = document.createElement('canvas');
  canvas.width = canvas.height = 128;
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  const sprite = new THREE.Sprite(
    new THREE.SpriteMaterial({ map: texture, depthTest: false, transparent: true }),
  );
  sprite.scale.set(width, width, 1);
  sprite.renderOrder = 31;
  let last = '';
  return {
    sprite,
    set(text, background) {
      if (text + background === last) return;
      last = text + background;
      const g = canvas.getContext('2d');
      g.clearRect(0, 0, 128, 128);
      g.fillStyle = background;
      g.beginPath();
      g.arc(64, 64, 60, 0, 2 * Math.PI);
      g.fill();
      g.fillStyle = '#0b1620';
      g.font = 'bold 84px "Liberation Sans", Arial, sans-serif';
      g.textAlign = 'center';
      g.textBaseline = 'middle';
      g.fillText(text, 64, 70);
      texture.needsUpdate = true;
    },
  };
}

function makeTarget(number) {
  const group = new THREE.Group();
  const label = makeBadge(0.035); // the number, above the ring
  label.sprite.position.set(0, 0.04, 0);
  const ring = new THREE.Mesh(
    new THREE.TorusGeometry(0.018, 0.0025, 8, 40),
    new THREE.MeshBasicMaterial({ color: COLOUR.todo, depthTest: false, transparent: true }),
  );
  ring.rotation.x = Math.PI / 2; // lying flat
  const dot = new THREE.Mesh(
    new THREE.SphereGeometry(0.004, 12, 8),
    new THREE.MeshBasicMaterial({ color: COLOUR.todo, depthTest: false, transparent: true }),
  );
  group.add(ring, dot, label.sprite);
  group.renderOrder = 30;
  ring.renderOrder = dot.renderOrder = 30;
  return {
    group,
    set(kind, pulse) {
      label.set(kind === 'done' ? '\u2713' : String(number), hex(COLOUR[kind]));
      ring.material.color.setHex(COLOUR[kind]);
      dot.material.color.setHex(COLOUR[kind]);
      ring.scale.setScalar(kind === 'now' ? 1 + 0.25 * pulse : 1);
    },
  };
}

// The page's side. `scene`: where targets are drawn (XR space); `worldRoot`: the group the
// feed's objects hang under; `send(obj)`: to the follower (false when the socket is down).
export function makeRegistration({ scene, worldRoot, send }) {
  const id = headsetId();
  const st = {
    id,
    state: 'none', // the follower's last word for this headset
    watch: null,
    message: '',
    refused: '',
    index: -1,
    count: 0,
    residualMm: null,
    T_xr_world: null,
    targets: [], // XR space, [x, y, z] each
  };
  const targetRoot = new THREE.Group();
  scene.add(targetRoot);
  let markers = [];
  let lastViewerMs = -Infinity;
  let viewer = null; // the last viewer pose {position, quaternion} (XR space)
  let watchedSpace = null;

  // Hello (the follower offers this headset's registration) once in each AR session and
  // after each reconnection during one; a tablet or laptop page never says it.
  let saidHello = false;
  function onOpen() {
    saidHello = false;
  }

  function onFeed(msg) {
    if (msg.headset !== id) return; // another headset's
    st.state = msg.state;
    st.message = msg.message || '';
    st.refused = msg.refused || '';
    st.index = Number.isInteger(msg.index) ? msg.index : -1;
    st.count = msg.count || st.count;
    st.watch = msg.watch || null;
    st.driftMm = msg.drift_mm;
    if (msg.residual_mm !== undefined) st.residualMm = msg.residual_mm;
    if (msg.state === 'registered' && msg.T_xr_world && !st.T_xr_world) {
      st.shownMs = performance.now(); // say so for a few seconds
    }
    if (msg.state === 'registered' && msg.T_xr_world) {
      const T = msg.T_xr_world;
      st.T_xr_world = T;
      worldRoot.position.set(...T.position);
      worldRoot.quaternion.set(...T.quaternion);
      worldRoot.updateMatrixWorld(true);
    } else if (msg.state === 'none') {
      st.T_xr_world = null;
    }
    if (msg.state !== 'collecting') clearTargets();
  }

  function clearTargets() {
    for (const m of markers) targetRoot.remove(m.group);
    markers = [];
  }

  // Start: targets in front of the viewer (level, facing where the viewer looks).
  function start() {
    if (!viewer) return false;
    const p = new THREE.Vector3(...viewer.position);
    const look = new THREE.Quaternion(...viewer.quaternion);
    const fwd = new THREE.Vector3(0, 0, -1).applyQuaternion(look);
    fwd.y = 0;
    if (fwd.lengthSq() < 1e-6) fwd.set(0, 0, -1);
    fwd.normalize();
    const right = new THREE.Vector3().crossVectors(fwd, new THREE.Vector3(0, 1, 0));
    const y = Math.min(TABLE_Y[1], Math.max(TABLE_Y[0], p.y - DROP));
    const centre = p.clone().addScaledVector(fwd, AHEAD);
    st.targets = LAYOUT.map(([r, a]) => {
      const t = centre.clone().addScaledVector(right, r).addScaledVector(fwd, a);
      return [round5(t.x), round5(y), round5(t.z)];
    });
    clearTargets();
    markers = st.targets.map((t, i) => {
      const m = makeTarget(i + 1);
      m.group.position.set(...t);
      targetRoot.add(m.group);
      return m;
    });
    st.state = 'starting';
    st.refused = '';
    return send({ type: 'registration', action: 'start', headset: id, targets: st.targets });
  }

  function take() {
    if (st.state === 'collecting') send({ type: 'registration', action: 'take', headset: id });
  }

  // The XR 'select' gesture (air tap, trigger, pinch): takes the point while registering,
  // starts a registration when one is needed (a headset without the DOM overlay has no
  // buttons); ignored while registered, so a tap during a scan changes nothing.
  function select() {
    if (st.state === 'collecting') take();
    else if (!st.T_xr_world || st.watch === 'drifted' || st.state === 'refused') start();
  }

  function cancel() {
    send({ type: 'registration', action: 'cancel', headset: id });
    clearTargets();
  }

  // Each frame: the viewer pose (AR), the watch's samples, the targets' colours, and whether
  // the feed's objects may be drawn. Returns what the banner should say, or null (the guide).
  // `overlay`: the page's buttons are shown in the headset (the DOM overlay); else the
  // banner says to air tap (the XR select gesture) instead.
  function frame(xrFrame, refSpace, nowMs, presenting, overlay = true) {
    if (!presenting) saidHello = false;
    else if (!saidHello) {
      saidHello = send({ type: 'registration', action: 'hello', headset: id });
    }
    if (presenting && xrFrame && refSpace) {
      if (watchedSpace !== refSpace) {
        watchedSpace = refSpace;
        refSpace.addEventListener('reset', () => {
          send({ type: 'registration', action: 'reset', headset: id });
        });
      }
      const pose = xrFrame.getViewerPose(refSpace);
      if (pose) {
        const { position: p, orientation: q } = pose.transform;
        viewer = {
          position: [p.x, p.y, p.z].map(round5),
          quaternion: [q.x, q.y, q.z, q.w].map(round5),
        };
        if (st.T_xr_world && nowMs - lastViewerMs >= VIEWER_EVERY_MS) {
          lastViewerMs = nowMs;
          send({ type: 'viewer_pose', headset: id, ...viewer });
        }
      }
    }
    const pulse = 0.5 + 0.5 * Math.sin(nowMs / 150);
    markers.forEach((m, i) => {
      m.set(i < st.index ? 'done' : i === st.index ? 'now' : 'todo', pulse);
    });
    if (!presenting) {
      // A tablet or laptop draws the feed's world as it is.
      worldRoot.position.set(0, 0, 0);
      worldRoot.quaternion.identity();
      worldRoot.visible = true;
      return null;
    }
    if (st.T_xr_world) {
      worldRoot.position.set(...st.T_xr_world.position);
      worldRoot.quaternion.set(...st.T_xr_world.quaternion);
    }
    const collecting = st.state === 'collecting' || st.state === 'starting';
    // A guide known to be misplaced is not drawn (as one that is not live is greyed).
    worldRoot.visible = Boolean(st.T_xr_world) && !collecting && st.watch !== 'drifted';
    return banner(collecting, nowMs, overlay);
  }

  function banner(collecting, nowMs, overlay) {
    const press = overlay ? 'Press Register' : 'Air tap';
    if (collecting) {
      const n = st.count || st.targets.length;
      const i = Math.max(0, st.index);
      return {
        cue: 'register',
        headline: `Registration: target ${i + 1} of ${n}`,
        detail:
          "Hold the probe's tip still on the blue ring for a second " +
          (overlay ? '(or press Take point).' : '(or air tap).'),
        refusal: st.refused ? `Not taken: ${st.refused}` : '',
        buttons: ['take', 'cancel'],
      };
    }
    if (st.state === 'refused') {
      return {
        cue: 'register',
        headline: 'Registration refused',
        detail: `${press} and touch the targets again.`,
        refusal: st.message,
        buttons: ['register'],
      };
    }
    if (!st.T_xr_world) {
      return {
        cue: 'register',
        headline: 'Register this headset first',
        detail:
          `${press}, then touch the tracked probe's tip to each of the 4 targets that ` +
          'appear in front of you.',
        refusal: '',
        buttons: ['register'],
      };
    }
    if (st.watch === 'drifted') {
      return {
        cue: 'register',
        headline: 'Re-register the headset',
        detail:
          `The headset's space has moved ${Math.round(st.driftMm)} mm from the tracker's: ` +
          `the guide is hidden until you register again. ${press}.`,
        refusal: '',
        buttons: ['register'],
      };
    }
    if (st.shownMs !== undefined && nowMs - st.shownMs < SHOW_DONE_MS) {
      return {
        cue: 'registered',
        headline: 'Headset registered',
        detail: st.message,
        refusal: '',
        buttons: ['register'],
        registered: true,
      };
    }
    return null; // registered: the guide
  }

  return {
    state: st,
    onOpen,
    onFeed,
    start,
    take,
    select,
    cancel,
    frame,
    targets: () => st.targets.map((t) => t.slice()),
    get viewer() {
      return viewer;
    },
  };
}
