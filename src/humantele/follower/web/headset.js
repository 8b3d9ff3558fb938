// The follower's headset page: the virtual transducer at the sonographer's pose, the real
// one as a ghost, the patient model's outline, the calibration prompt and the alignment cue.
//
// WebXR immersive-ar where the browser offers it (the headset), else a 3D view with orbit
// controls (tablet, laptop). Everything comes from the follower's feed, a WebSocket on this
// page's origin; the page echoes, for a sample of frames, which pose it drew (the feed's
// latency figure). Frames: the feed's world frame is three.js's (y up, metres, quaternions
// x, y, z, w); in AR the page draws in the headset's local-floor space, and the feed's
// objects hang under a root placed at T_xr_world, the follower's registration of the two
// (registration.js; nothing from the feed is drawn in AR before there is one).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import {
  CLOSE,
  COLOURS,
  ON_TARGET,
  STALE_AFTER_MS,
  describeMove,
  errors,
  grade,
  guideState,
  linkText,
} from './cue.js';
import { makeRegistration } from './registration.js';
import {
  makeArrow,
  makeBed,
  makeLabel,
  makeOutline,
  makePanel,
  makeTransducer,
} from './scene.js';

const LOOK_ABOVE = new THREE.Vector3(0, 0.1, 0); // the view centres on the probe's handle
const GLIDE_S = 0.3; // time constant of the view following the probe
const ECHO_EVERY_MS = 50;
const PANEL_COLOURS = { ...COLOURS, register: 0xb48cff, registered: 0x2fbf71, calibrating: 0x4aa3ff };
const ARROW_COLOUR = 0xff4fd8; // magenta: unlike the probes, the outline and the room // at most 20 "drawn" echoes a second
const LANDMARK_NAMES = { xiphoid: 'Xiphoid', left: 'Left side', right: 'Right side', bed: 'Bed' };
const LANDMARKS = Object.keys(LANDMARK_NAMES);

const $ = (id) => document.getElementById(id);
const feedPath = document.querySelector('meta[name="feed-path"]').content;

// --- what the feed told us -----------------------------------------------------------------

const state = {
  socket: false,
  link: null,
  virtual: null, // + arrivedMs (performance.now() at arrival)
  probe: null,
  model: null,
  calibration: null,
  devices: null, // the follower's devices: { headset_stream_stalled, force_stale }
  frozen: false,
  messages: 0,
  badMessages: 0,
};
let socket = null;

// --- pairing: the feed takes only pages with the follower's pairing code ---------------------
// Asked once and kept in this browser (localStorage); an address ending in #code=... pairs too.
// A refused code (close 4401) is forgotten and asked again; too many wrong ones (4429): wait.
const PAIRING_STORE = 'humantele-pairing-code';
const CLOSE_UNAUTHORIZED = 4401;
const CLOSE_THROTTLED = 4429;
const digitsOnly = (text) => text.replace(/[\s-]/g, '');

function pairingCode() {
  const m = /(?:^#|&)code=([^&]+)/.exec(location.hash);
  if (m) {
    localStorage.setItem(PAIRING_STORE, digitsOnly(decodeURIComponent(m[1])));
    history.replaceState(null, '', location.pathname + location.search);
  }
  return localStorage.getItem(PAIRING_STORE);
}

function askPairing(note, refused = false) {
  $('pairing-note').textContent = note;
  $('pairing').dataset.refused = String(refused);
  if (refused) $('pairing-code').value = '';
  $('pairing').hidden = false;
  document.body.dataset.pairing = 'needed';
  $('pairing-code').focus();
}

$('pairing').addEventListener('submit', (ev) => {
  ev.preventDefault();
  const code = digitsOnly($('pairing-code').value);
  if (!/^[0-9]{8}$/.test(code)) {
    $('pairing-note').textContent = 'The pairing code is 8 digits, for example 1234 5678.';
    return;
  }
  localStorage.setItem(PAIRING_STORE, code);
  $('pairing').hidden = true;
  delete document.body.dataset.pairing;
  connect();
});

// Whether the feed refused this page's code (then the page asks for it, not reconnecting).
function pairingRefused(ev) {
  if (ev.code === CLOSE_UNAUTHORIZED) {
    localStorage.removeItem(PAIRING_STORE);
    askPairing('The follower did not accept that code. Type the pairing code it printed at its start.', true);
    return true;
  }
  if (ev.code === CLOSE_THROTTLED) {
    askPairing('Too many wrong codes: wait a minute, then type the code again.', true);
    return true;
  }
  return false;
}

function connect(delayMs = 500) {
  const code = pairingCode();
  if (!code) {
    askPairing(
      'Type the pairing code the follower printed beside this page\'s address ' +
        '(in its terminal or log, after “pairing code”). This browser keeps it.',
    );
    return;
  }
  const scheme = location.protocol === 'https:' ? 'wss:' : 'ws:';
  socket = new WebSocket(`${scheme}//${location.host}${feedPath}?code=${encodeURIComponent(code)}`);
  socket.onopen = () => {
    state.socket = true;
    delayMs = 500;
    registration.onOpen();
  };
  socket.onmessage = (ev) => {
    if (state.frozen) return;
    let msg;
    try {
      msg = JSON.parse(ev.data);
    } catch {
      state.badMessages++;
      return;
    }
    state.messages++;
    onMessage(msg);
  };
  socket.onclose = (ev) => {
    state.socket = false;
    if (pairingRefused(ev)) return;
    setTimeout(() => connect(Math.min(5000, delayMs * 2)), delayMs);
  };
}

const calibrationSteps = []; // the landmarks the feed asked for, in the order heard

function onMessage(msg) {
  switch (msg.type) {
    case 'virtual_probe':
      if (Array.isArray(msg.position) && Array.isArray(msg.quaternion)) {
        msg.arrivedMs = performance.now();
        state.virtual = msg;
      }
      break;
    case 'probe':
      state.probe = msg;
      break;
    case 'model':
      setModel(msg);
      break;
    case 'calibration':
      state.calibration = msg;
      if (msg.calibrating && msg.step !== calibrationSteps[calibrationSteps.length - 1]) {
        calibrationSteps.push(msg.step); // heard, in order (a starved page may draw fewer)
        if (calibrationSteps.length > 32) calibrationSteps.shift();
      }
      break;
    case 'link':
      state.link = msg.state;
      break;
    case 'registration':
      registration.onFeed(msg);
      break;
    case 'devices':
      state.devices = msg;
      break;
  }
}

// --- the scene -----------------------------------------------------------------------------

const renderer = new THREE.WebGLRenderer({ antialias: true, alpha: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.xr.enabled = true;
$('view').appendChild(renderer.domElement);

const scene = new THREE.Scene();
const background = new THREE.Color(0x1b2129);
scene.background = background;
scene.add(new THREE.HemisphereLight(0xffffff, 0x40464f, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(0.5, 2, 1);
scene.add(sun);
const grid = new THREE.GridHelper(4, 40, 0x3a4550, 0x2a323b);
scene.add(grid);

const camera = new THREE.PerspectiveCamera(45, window.innerWidth / window.innerHeight, 0.01, 20);
camera.position.set(1.2, 1.6, 1.0);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0.35, 0.9, -0.15);
controls.enableDamping = true;
let followView = true; // the view keeps the probes in the middle until the user moves it
controls.addEventListener('start', () => {
  followView = false;
});
let viewPlaced = false;

const virtual = makeTransducer({ colour: COLOURS.green });
const ghost = makeTransducer({ colour: 0xe8f1ff, opacity: 0.4, beam: false, edges: true });
const arrow = makeArrow(ARROW_COLOUR);
const label = makeLabel();
virtual.group.visible = ghost.group.visible = arrow.group.visible = false;
label.sprite.visible = false;
// The feed's objects, in the tracker's world: under worldRoot (identity on a tablet or
// laptop; T_xr_world in AR once registered).
const worldRoot = new THREE.Group();
scene.add(worldRoot);
worldRoot.add(virtual.group, ghost.group, arrow.group, label.sprite);
const objects = { virtual: virtual.group, ghost: ghost.group, arrow: arrow.group, label: label.sprite };
const outlineRoot = new THREE.Group();
worldRoot.add(outlineRoot);
const registration = makeRegistration({ scene, worldRoot, send: sendToFeed });

function sendToFeed(obj) {
  if (!socket || socket.readyState !== WebSocket.OPEN) return false;
  socket.send(JSON.stringify(obj));
  return true;
}
let outline = null;
let bed = null;
let outlineOn = true;

function setModel(model) {
  if (!Array.isArray(model.center) || !Array.isArray(model.semi_axes)) return;
  state.model = model;
  for (const o of [outline && outline.group, bed]) if (o) outlineRoot.remove(o);
  outline = makeOutline(model);
  bed = makeBed(model);
  outline.group.visible = outlineOn;
  outlineRoot.add(bed, outline.group);
  if (followView) viewPlaced = false; // look again, now from the patient's side
}

function setPose(object, msg) {
  object.position.set(msg.position[0], msg.position[1], msg.position[2]);
  object.quaternion.set(msg.quaternion[0], msg.quaternion[1], msg.quaternion[2], msg.quaternion[3]);
}

// Place the view once: from above the patient's right side (where the follower stands),
// toward the head, so moves along and across the body both show.
function placeView(target) {
  const offset = new THREE.Vector3(-0.2, 0.38, 0.38);
  if (state.model) offset.applyQuaternion(new THREE.Quaternion(...state.model.quaternion));
  controls.target.copy(target);
  camera.position.copy(target).add(offset);
  viewPlaced = true;
}

// --- the cue ------------------------------------------------------------------------------

function hex(c) {
  return `#${c.toString(16).padStart(6, '0')}`;
}

const hud = { key: '' };
let lastGuide = { live: false, reason: '' };
function setHud(view) {
  const key = JSON.stringify(view);
  if (key === hud.key) return;
  hud.key = key;
  document.body.dataset.cue = view.cue;
  $('headline').textContent = view.headline;
  $('detail').textContent = view.detail;
  $('refusal').textContent = view.refusal || '';
  $('refusal').hidden = !view.refusal;
  $('err-mm').textContent = view.mm;
  $('err-deg').textContent = view.deg;
  $('age').textContent = view.age;
  $('link').textContent = view.link;
  $('force').textContent = view.force;
  for (const [name, el] of Object.entries(REG_BUTTONS)) el.hidden = !view.buttons.includes(name);
  REG_BUTTONS.register.textContent = view.registered ? 'Register again' : 'Register';
  REG_BUTTONS.register.className = view.registered ? 'quiet' : '';
  const steps = $('steps');
  steps.hidden = !view.calibrating;
  $('landmarks').toggleAttribute('hidden', !view.calibrating); // an SVG element: no .hidden
  for (const el of [...steps.children, ...$('landmarks').querySelectorAll('[data-landmark]')]) {
    const i = LANDMARKS.indexOf(el.dataset.landmark);
    el.setAttribute('class', i < view.stepIndex ? 'done' : i === view.stepIndex ? 'now' : '');
  }
}

let lastUpdateMs = performance.now();
function update(nowMs) {
  const cal = state.calibration;
  const calibrating = Boolean(cal && cal.calibrating);
  const guide = guideState(state, nowMs);
  lastGuide = guide;
  const v = state.virtual;
  const p = state.probe && state.probe.position ? state.probe : null;
  const view = {
    cue: 'stale',
    headline: '',
    detail: '',
    refusal: '',
    mm: '–',
    deg: '–',
    age: guide.ageMs === undefined ? '–' : `${Math.round(guide.ageMs)} ms`,
    link: state.socket ? linkText(state, guide) : 'no feed',
    force: p && Array.isArray(p.force) ? `${Math.hypot(...p.force).toFixed(1)} N` : '–',
    calibrating,
    stepIndex: -1,
    buttons: [],
  };

  ghost.group.visible = Boolean(p);
  if (p) setPose(ghost.group, p);
  virtual.group.visible = Boolean(v) && !calibrating;
  if (v) setPose(virtual.group, v);
  arrow.group.visible = false;

  if (calibrating) {
    const step = LANDMARKS.indexOf(cal.step);
    view.cue = 'calibrating';
    view.stepIndex = step;
    view.headline = `Calibration ${step + 1} of 4: ${LANDMARK_NAMES[cal.step] || cal.step}`;
    view.detail = cal.prompt ? cal.prompt[0].toUpperCase() + cal.prompt.slice(1) + '.' : '';
    if (cal.event === 'refused') view.refusal = `Not taken: ${cal.message}`;
    label.sprite.visible = false;
  } else if (!v || !guide.live) {
    view.cue = 'stale';
    view.headline = v ? 'Guide paused: not live' : 'Waiting for the sonographer';
    view.detail = guide.reason;
    virtual.setColour(COLOURS.stale);
    virtual.setOpacity(0.55);
    label.set('NOT LIVE: hold still', '#5b6168');
    label.sprite.visible = Boolean(v);
  } else {
    const err = p ? errors(p, v) : null;
    const g = err ? grade(err) : 'amber';
    view.cue = g;
    virtual.setColour(COLOURS[g]);
    virtual.setOpacity(1);
    if (err) {
      view.mm = `${err.mm.toFixed(1)} mm`;
      view.deg = `${err.deg.toFixed(1)}°`;
      if (g === 'green') {
        view.headline = 'On target: hold the probe here';
        view.detail = 'Follow the coloured probe as it moves.';
      } else {
        view.headline = `Move the probe ${err.mm.toFixed(0)} mm along the arrow`;
        const move = describeMove(p, v, state.model);
        const turn = [
          err.tilt >= 2 ? `tilt ${err.tilt.toFixed(0)}°` : '',
          err.twist >= 2 ? `twist ${err.twist.toFixed(0)}°` : '',
        ]
          .filter(Boolean)
          .join(', ');
        const words = [move, turn ? `then ${turn} to match` : ''].filter(Boolean).join('; ');
        view.detail = words ? words[0].toUpperCase() + words.slice(1) + '.' : '';
      }
      label.set(`${err.mm.toFixed(0)} mm  ${err.deg.toFixed(0)}°`, hex(COLOURS[g]));
      if (err.mm >= ON_TARGET.mm) {
        arrow.set(ghost.group.position, virtual.group.position);
        arrow.group.visible = true;
      }
    } else {
      view.headline = 'Real probe not seen by the tracker';
      view.detail = 'Keep the probe and its markers in view of the headset.';
      label.set('probe not tracked', '#5b6168');
    }
    label.sprite.visible = true;
  }
  const devices = state.devices || {};
  if (devices.headset_stream_stalled) {
    // no frames from the headset (Wi-Fi drop, headset asleep): the probe's last pose is old
    view.headline = 'Headset stream stalled';
    view.detail = 'The tracker gets no frames from the headset; reconnecting.';
    ghost.group.visible = false;
    arrow.group.visible = false;
  }
  if (devices.force_stale) view.force = 'no force (board?)';
  if (v) {
    label.sprite.position.copy(virtual.group.position);
    label.sprite.position.y += 0.2;
  }
  registrationView(view, nowMs);
  placePanel(view);
  setHud(view);
  if (outline) outline.group.visible = outlineOn;
  for (const o of [...Object.values(objects), outline && outline.group]) {
    if (o && o.userData.hiddenForTest) o.visible = false; // a test hid it
  }

  const probe = v && !calibrating ? virtual.group : p ? ghost.group : null;
  const target = probe && probe.position.clone().add(LOOK_ABOVE);
  if (target && !state.frozen) {
    if (!viewPlaced) placeView(target);
    else if (followView) {
      // Glide toward the probe, camera and target together: the view keeps its angle.
      const dt = Math.min(1, (nowMs - lastUpdateMs) / 1000);
      const step = target.sub(controls.target).multiplyScalar(1 - Math.exp(-dt / GLIDE_S));
      controls.target.add(step);
      camera.position.add(step);
    }
  }
  lastUpdateMs = nowMs;
}

// --- registration (registration.js): what the banner says in AR until registered -----

const REG_BUTTONS = { register: $('register'), take: $('reg-take'), cancel: $('reg-cancel') };
REG_BUTTONS.register.addEventListener('click', () => registration.start());
REG_BUTTONS.take.addEventListener('click', () => registration.take());
REG_BUTTONS.cancel.addEventListener('click', () => registration.cancel());

const panel = makePanel(0.36);
scene.add(panel.group);

function presentingNow() {
  return renderer.xr.isPresenting && xrSession !== null;
}

// Without the DOM overlay (immersive-vr, some headsets) the banner is drawn in the scene,
// 0.9 m ahead of the viewer in the top of its view (HoloLens 2: 29 degrees high), following
// the head: the middle of the view, where the work and the targets are, stays clear.
function placePanel(view) {
  const v = registration.viewer;
  panel.group.visible = presentingNow() && !xr.domOverlay && Boolean(v);
  if (!panel.group.visible) return;
  panel.set(view.headline, view.detail, view.refusal, PANEL_COLOURS[view.cue] || 0x8b9096);
  const q = new THREE.Quaternion(...v.quaternion);
  const ahead = new THREE.Vector3(0, 0.15, -0.9).applyQuaternion(q);
  panel.group.position.set(...v.position).add(ahead);
  panel.group.quaternion.copy(q);
}

function registrationView(view, nowMs) {
  const presenting = presentingNow();
  const xrFrame = presenting ? renderer.xr.getFrame() : null;
  const space = renderer.xr.getReferenceSpace();
  const reg = registration.frame(xrFrame, space, nowMs, presenting, xr.domOverlay);
  if (reg && !view.calibrating) {
    Object.assign(view, reg);
    label.sprite.visible = false;
  } else if (presenting && !view.calibrating) {
    view.buttons = ['register']; // registered: may register again
    view.registered = true;
  }
}

// --- drawing, and the echo for the latency figure -------------------------------------------

let frames = 0;
let lastEchoId = 0;
let lastEchoMs = -Infinity;

function frame() {
  const now = state.frozen ? state.frozenAt : performance.now();
  update(now);
  if (!renderer.xr.isPresenting) controls.update();
  const drawn = state.virtual && !state.frozen ? state.virtual.pose_id : 0;
  const tDraw = performance.now();
  renderer.render(scene, camera);
  frames++;
  if (drawn && drawn !== lastEchoId && tDraw - lastEchoMs >= ECHO_EVERY_MS && state.socket) {
    lastEchoId = drawn;
    lastEchoMs = tDraw;
    const echo = { type: 'drawn', pose_id: drawn, draw_to_send_ms: 0 };
    echo.draw_to_send_ms = Math.max(0, performance.now() - tDraw);
    socket.send(JSON.stringify(echo));
  }
}

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});

// --- controls and WebXR --------------------------------------------------------------------

$('outline').addEventListener('click', () => {
  outlineOn = !outlineOn;
  $('outline').setAttribute('aria-pressed', String(outlineOn));
});
$('recentre').addEventListener('click', () => {
  followView = true;
  viewPlaced = false;
});

let xrSession = null;
async function enterAR() {
  const session = await navigator.xr.requestSession(xr.mode, {
    requiredFeatures: ['local-floor'],
    optionalFeatures: ['dom-overlay'],
    domOverlay: { root: $('hud') },
  });
  renderer.xr.setReferenceSpaceType('local-floor');
  await renderer.xr.setSession(session);
  xrSession = session;
  // air tap, trigger, pinch: starts or takes a point while a registration is needed
  session.addEventListener('select', () => registration.select());
  scene.background = null; // the room shows through (immersive-vr on a see-through display:
  // black is transparent)
  grid.visible = false;
  document.body.classList.add('xr');
  xr.domOverlay = Boolean(session.domOverlayState); // else the banner is drawn in the scene
  session.addEventListener('end', () => {
    xrSession = null;
    panel.group.visible = false;
    scene.background = background;
    grid.visible = true;
    document.body.classList.remove('xr');
  });
}

// immersive-ar where offered; else immersive-vr, which HoloLens 2's Edge offers instead
// (docs/hololens.md): on its see-through display the room still shows.
async function offerAR() {
  for (const mode of ['immersive-ar', 'immersive-vr']) {
    if (!xr.mode && navigator.xr && (await navigator.xr.isSessionSupported(mode))) xr.mode = mode;
  }
  const supported = Boolean(xr.mode);
  xr.supported = supported;
  const button = $('enter-ar');
  button.hidden = !supported;
  if (supported) {
    button.addEventListener('click', () =>
      enterAR().catch((e) => {
        xr.error = String(e);
        $('detail').textContent = `Could not start AR: ${e.message || e}`;
      }),
    );
  }
}

// --- for tests: the camera, the drawn objects, a way to hold still ------------------------

const xr = { supported: false, error: null, mode: null, domOverlay: false };
window.headset = {
  state,
  xr,
  thresholds: { ON_TARGET, CLOSE, STALE_AFTER_MS },
  get frames() {
    return frames;
  },
  get presenting() {
    return renderer.xr.isPresenting && xrSession !== null;
  },
  // The page's camera: column-major 4x4 matrices as three.js keeps them, and the canvas size.
  camera() {
    camera.updateMatrixWorld();
    return {
      projection: camera.projectionMatrix.elements.slice(),
      view: camera.matrixWorldInverse.elements.slice(),
      width: renderer.domElement.clientWidth,
      height: renderer.domElement.clientHeight,
    };
  },
  matrixWorld(name) {
    const o = name === 'outline' ? outline && outline.group : objects[name];
    if (!o) return null;
    o.updateMatrixWorld(true);
    return o.matrixWorld.elements.slice();
  },
  visible(name) {
    const o = name === 'outline' ? outline && outline.group : objects[name];
    return Boolean(o && o.visible && worldRoot.visible); // in AR: not before registration
  },
  // Stop taking feed messages (the picture holds still) or take them again.
  freeze(on) {
    state.frozen = Boolean(on);
    state.frozenAt = performance.now(); // the picture's clock stops too (no ageing)
  },
  // Hide or show one drawn object (the next frame draws without it).
  show(name, on) {
    const o = name === 'outline' ? outline && outline.group : objects[name];
    if (o) o.userData.hiddenForTest = !on;
  },
  // Hide or show the text laid over the view (a test's pictures of the 3D view alone).
  showHud(on) {
    $('hud').style.visibility = on ? 'visible' : 'hidden';
  },
  colour() {
    return virtual.materials[0].color.getHex();
  },
  // The landmarks the feed asked for since the last clear, in order (each step once).
  calibrationSteps(clear = false) {
    const steps = [...calibrationSteps];
    if (clear) calibrationSteps.length = 0;
    return steps;
  },
  hud() {
    return {
      cue: document.body.dataset.cue,
      headline: $('headline').textContent,
      detail: $('detail').textContent,
      refusal: $('refusal').hidden ? '' : $('refusal').textContent,
      link: $('link').textContent,
      mm: $('err-mm').textContent,
      deg: $('err-deg').textContent,
      steps: [...$('steps').children].map((li) => li.className),
      guide: lastGuide,
      colour: virtual.materials[0].color.getHex(),
      buttons: Object.keys(REG_BUTTONS).filter((k) => !REG_BUTTONS[k].hidden),
      registration: { ...registration.state, targets: undefined },
    };
  },
  registration,
  get session() {
    return xrSession;
  },
  // The banner drawn in the scene (a session without the DOM overlay): shown, and its text.
  panel() {
    return { visible: panel.group.visible && presentingNow(), text: panel.text };
  },
};

connect();
offerAR();
renderer.setAnimationLoop(frame);
