// The things the headset page draws, in the feed's world frame (y up, metres).
//
// A transducer is drawn in its tip frame: origin at the centre of the face, +z along the beam
// (into the patient), the array along x, the handle up along -z, the orientation marker on
// the +x side of the face.

import * as THREE from 'three';

const FACE = { x: 0.046, y: 0.014, z: 0.012 };
const HANDLE = { x: 0.032, y: 0.024, z: 0.095 };
const BEAM_DEPTH = 0.07;

function box(sx, sy, sz, z, material) {
  const mesh = new THREE.Mesh(new THREE.BoxGeometry(sx, sy, sz), material);
  mesh.position.z = z;
  return mesh;
}

// A transducer: face, neck, handle, cable and marker; the beam as a translucent fan.
// Returns {group, setColour(hex), materials}.
export function makeTransducer({ colour, opacity = 1, beam = true, edges = false }) {
  const group = new THREE.Group();
  const body = new THREE.MeshStandardMaterial({
    color: colour,
    roughness: 0.5,
    metalness: 0.05,
    transparent: true,
    opacity,
    depthWrite: opacity >= 1,
  });
  const face = box(FACE.x, FACE.y, FACE.z, -FACE.z / 2, body);
  const neck = box(0.038, 0.02, 0.02, -FACE.z - 0.01, body);
  const handle = box(HANDLE.x, HANDLE.y, HANDLE.z, -FACE.z - 0.02 - HANDLE.z / 2, body);
  const cable = new THREE.Mesh(new THREE.CylinderGeometry(0.005, 0.005, 0.04, 12), body);
  cable.rotation.x = Math.PI / 2;
  cable.position.z = -FACE.z - 0.02 - HANDLE.z - 0.02;
  const marker = new THREE.Mesh(
    new THREE.SphereGeometry(0.004, 12, 8),
    new THREE.MeshBasicMaterial({ color: 0xffffff, transparent: opacity < 1, opacity }),
  );
  marker.position.set(FACE.x / 2 + 0.003, 0, -FACE.z / 2);
  group.add(face, neck, handle, cable, marker);
  const materials = [body];
  if (edges) {
    const lines = new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.9 });
    for (const part of [face, neck, handle]) {
      const e = new THREE.LineSegments(new THREE.EdgesGeometry(part.geometry), lines);
      e.position.copy(part.position);
      group.add(e);
    }
    materials.push(lines);
  }
  if (beam) {
    // The imaging plane (x-z), widening with depth: where the image comes from.
    const w0 = FACE.x / 2;
    const w1 = FACE.x / 2 + 0.015;
    const shape = new THREE.BufferGeometry();
    shape.setAttribute(
      'position',
      new THREE.Float32BufferAttribute(
        [-w0, 0, 0, w0, 0, 0, w1, 0, BEAM_DEPTH, -w0, 0, 0, w1, 0, BEAM_DEPTH, -w1, 0, BEAM_DEPTH],
        3,
      ),
    );
    const fan = new THREE.MeshBasicMaterial({
      color: colour,
      transparent: true,
      opacity: 0.3,
      side: THREE.DoubleSide,
      depthWrite: false,
    });
    group.add(new THREE.Mesh(shape, fan));
    materials.push(fan);
  }
  return {
    group,
    materials,
    setColour(hex) {
      for (const m of materials) m.color.setHex(hex);
    },
    // Solid when live, see-through when not (the body only; the beam stays faint).
    setOpacity(value) {
      body.opacity = value;
      body.depthWrite = value >= 1;
    },
  };
}

// An arrow from a point toward another, drawn over everything: as long as the gap, but at
// least MIN_ARROW so its direction can be seen when the gap is small.
const MIN_ARROW = 0.06;
export function makeArrow(colour) {
  // Transparent (drawn after the see-through probes) and never hidden behind anything.
  const material = new THREE.MeshLambertMaterial({
    color: colour,
    emissive: colour,
    emissiveIntensity: 0.45, // bright, yet shaded: a cone seen end-on still reads as a cone
    depthTest: false,
    depthWrite: false,
    transparent: true,
    opacity: 0.95,
  });
  const shaft = new THREE.Mesh(new THREE.CylinderGeometry(0.004, 0.004, 1, 12), material);
  const head = new THREE.Mesh(new THREE.ConeGeometry(0.012, 1, 16), material);
  const group = new THREE.Group();
  group.add(shaft, head);
  group.renderOrder = 10;
  shaft.renderOrder = 10;
  head.renderOrder = 10;
  const up = new THREE.Vector3(0, 1, 0);
  return {
    group,
    material,
    set(from, to) {
      const d = new THREE.Vector3().subVectors(to, from);
      const gap = d.length();
      if (gap < 1e-6) return;
      const len = Math.max(gap, MIN_ARROW);
      const headLen = Math.min(0.026, 0.4 * len);
      group.position.copy(from);
      group.quaternion.setFromUnitVectors(up, d.clone().divideScalar(gap));
      shaft.scale.set(1, len - headLen, 1);
      shaft.position.y = (len - headLen) / 2;
      head.scale.set(1, headLen, 1);
      head.position.y = len - headLen / 2;
    },
  };
}

// The fitted ellipsoid as an outline over the scanning region (its long semi-axis is metres
// long, the paper's "very large"): cross-section rings along the body and lines along it.
export function makeOutline(model, halfLength = 0.3, colour = 0x8fe3ff) {
  const [c, b, a] = model.semi_axes; // along patient x (body), y (up), z (lateral)
  const material = new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.85 });
  const group = new THREE.Group();
  const span = Math.min(halfLength, 0.95 * c);
  for (let i = -3; i <= 3; i++) {
    const x = (span * i) / 3;
    const s = Math.sqrt(Math.max(0, 1 - (x / c) ** 2));
    const pts = [];
    for (let k = 0; k <= 64; k++) {
      const t = (2 * Math.PI * k) / 64;
      pts.push(new THREE.Vector3(x, b * s * Math.sin(t), a * s * Math.cos(t)));
    }
    group.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(pts), material));
  }
  for (let k = 0; k < 12; k++) {
    const t = (2 * Math.PI * k) / 12;
    const pts = [];
    for (let j = 0; j <= 24; j++) {
      const x = -span + (2 * span * j) / 24;
      const s = Math.sqrt(Math.max(0, 1 - (x / c) ** 2));
      pts.push(new THREE.Vector3(x, b * s * Math.sin(t), a * s * Math.cos(t)));
    }
    group.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(pts), material));
  }
  placeInPatientFrame(group, model);
  return { group, material };
}

// The bed under the patient: a translucent slab at the model's bed height. Lambert shading:
// a flat matte slab looks the same as with the physically based material (rough, not
// metallic), and it covers much of the view, so its per-pixel cost counts (in software
// WebGL, 0.048 -> 0.037 CPU-s of the GPU process a frame at 960 x 600, 2026-11-29).
export function makeBed(model) {
  const mesh = new THREE.Mesh(
    new THREE.BoxGeometry(1.9, 0.01, 0.8),
    new THREE.MeshLambertMaterial({ color: 0x4a545e, transparent: true, opacity: 0.92 }),
  );
  placeInPatientFrame(mesh, model);
  mesh.position.y = model.bed_y - 0.005;
  return mesh;
}

function placeInPatientFrame(object, model) {
  object.position.set(model.center[0], model.center[1], model.center[2]);
  object.quaternion.set(...model.quaternion);
}

// A text label that faces the camera (readable in the headset too), width in metres.
export function makeLabel(width = 0.1) {
  const canvas = document.createElement('canvas');
  canvas.width = 512;
  canvas.height = 128;
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  const sprite = new THREE.Sprite(
    new THREE.SpriteMaterial({ map: texture, depthTest: false, transparent: true }),
  );
  sprite.scale.set(width, width / 4, 1);
  sprite.renderOrder = 20;
  let last = '';
  return {
    sprite,
    set(text, background) {
      const key = text + background;
      if (key === last) return;
      last = key;
      const g = canvas.getContext('2d');
      g.clearRect(0, 0, canvas.width, canvas.height);
      g.fillStyle = background;
      g.beginPath();
      g.roundRect(4, 4, canvas.width - 8, canvas.height - 8, 28);
      g.fill();
      g.fillStyle = '#ffffff';
      g.font = 'bold 56px "Liberation Sans", Arial, sans-serif';
      g.textAlign = 'center';
      g.textBaseline = 'middle';
      g.fillText(text, canvas.width / 2, canvas.height / 2 + 2, canvas.width - 40);
      texture.needsUpdate = true;
    },
  };
}

// The banner as a panel in the scene, for a session without the DOM overlay: the headline,
// the detail (wrapped) and a refusal, on a dark card with the cue's colour at its left;
// width in metres. set() redraws only when the text changes.
export function makePanel(width = 0.5) {
  const canvas = document.createElement('canvas');
  canvas.width = 1024;
  canvas.height = 400;
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  const mesh = new THREE.Mesh(
    new THREE.PlaneGeometry(width, (width * canvas.height) / canvas.width),
    new THREE.MeshBasicMaterial({ map: texture, transparent: true, depthTest: false }),
  );
  mesh.renderOrder = 40;
  const group = new THREE.Group();
  group.add(mesh);
  group.visible = false;
  const panel = { group, text: '' };
  panel.set = (headline, detail, refusal, colour) => {
    const text = [headline, detail, refusal].join('\n');
    const key = text + colour;
    if (key === panel.key) return;
    panel.key = key;
    panel.text = text;
    const g = canvas.getContext('2d');
    g.clearRect(0, 0, canvas.width, canvas.height);
    g.fillStyle = 'rgba(20, 24, 30, 0.92)';
    g.beginPath();
    g.roundRect(0, 0, canvas.width, canvas.height, 28);
    g.fill();
    g.fillStyle = `#${colour.toString(16).padStart(6, '0')}`;
    g.fillRect(0, 0, 22, canvas.height);
    g.fillStyle = '#ffffff';
    g.font = 'bold 52px "Liberation Sans", Arial, sans-serif';
    g.textBaseline = 'top';
    g.fillText(headline, 50, 30, canvas.width - 80);
    g.font = '36px "Liberation Sans", Arial, sans-serif';
    let y = 105;
    for (const line of wrap(g, detail, canvas.width - 90)) {
      g.fillText(line, 50, y);
      y += 46;
    }
    if (refusal) {
      g.fillStyle = '#ff8f92';
      for (const line of wrap(g, refusal, canvas.width - 90)) {
        g.fillText(line, 50, y + 10);
        y += 46;
      }
    }
    texture.needsUpdate = true;
  };
  return panel;
}

function wrap(g, text, maxWidth) {
  const lines = [];
  let line = '';
  for (const word of (text || '').split(' ')) {
    const next = line ? `${line} ${word}` : word;
    if (g.measureText(next).width > maxWidth && line) {
      lines.push(line);
      line = word;
    } else line = next;
  }
  if (line) lines.push(line);
  return lines.slice(0, 6);
}
