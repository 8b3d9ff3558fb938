// The alignment cue and the guide's state, as pure functions of the feed's objects.
//
// Frames: the feed's world frame (y up, metres), quaternions [x, y, z, w] as three.js uses
// them; the patient frame of the model: x head to feet, y up, z from the patient's left to
// right. Errors are shown in mm and degrees.

import * as THREE from 'three';

// Colour of the virtual probe by alignment error (both must hold):
//   green: within 5 mm and 5 deg (on target), amber: within 15 mm and 15 deg, red: further.
export const ON_TARGET = { mm: 5, deg: 5 };
export const CLOSE = { mm: 15, deg: 15 };
// The guide is not live when the pose is older than this (ms since the sonographer sent it).
export const STALE_AFTER_MS = 500;

export const COLOURS = {
  green: 0x2fbf71,
  amber: 0xf2a900,
  red: 0xe5484d,
  stale: 0x8b9096,
};

const _qa = new THREE.Quaternion();
const _qb = new THREE.Quaternion();

export function quaternion(q) {
  return new THREE.Quaternion(q[0], q[1], q[2], q[3]);
}

export function vector(p) {
  return new THREE.Vector3(p[0], p[1], p[2]);
}

// Angle (deg) of the rotation between two quaternions [x, y, z, w].
export function angleDeg(qa, qb) {
  _qa.set(qa[0], qa[1], qa[2], qa[3]).normalize();
  _qb.set(qb[0], qb[1], qb[2], qb[3]).normalize();
  const dot = Math.min(1, Math.abs(_qa.dot(_qb)));
  return THREE.MathUtils.radToDeg(2 * Math.acos(dot));
}

// Tilt (deg between the beams, the tip frames' +z) and twist (deg about the beam once the
// beams agree) from the real probe's orientation to the virtual one's.
export function tiltTwistDeg(qReal, qVirtual) {
  const qr = quaternion(qReal).normalize();
  const qv = quaternion(qVirtual).normalize();
  const zr = new THREE.Vector3(0, 0, 1).applyQuaternion(qr);
  const zv = new THREE.Vector3(0, 0, 1).applyQuaternion(qv);
  const tilt = THREE.MathUtils.radToDeg(zr.angleTo(zv));
  const align = new THREE.Quaternion().setFromUnitVectors(zr, zv);
  const xr = new THREE.Vector3(1, 0, 0).applyQuaternion(qr).applyQuaternion(align);
  const xv = new THREE.Vector3(1, 0, 0).applyQuaternion(qv);
  const twist = THREE.MathUtils.radToDeg(xr.angleTo(xv));
  return { tilt, twist };
}

export function errors(probe, virtual) {
  const mm = vector(probe.position).distanceTo(vector(virtual.position)) * 1000;
  const deg = angleDeg(probe.quaternion, virtual.quaternion);
  return { mm, deg, ...tiltTwistDeg(probe.quaternion, virtual.quaternion) };
}

export function grade(err) {
  if (err.mm < ON_TARGET.mm && err.deg < ON_TARGET.deg) return 'green';
  if (err.mm < CLOSE.mm && err.deg < CLOSE.deg) return 'amber';
  return 'red';
}

// Is the guide live? {live, reason, ageMs}; the reason is in words a novice understands.
// state: {socket: bool, link: 'connected'|..., virtual: feed object with .arrivedMs, calibrating}
export function guideState(state, nowMs) {
  if (!state.socket) {
    return { live: false, reason: 'No connection to the clinic computer. Reconnecting…' };
  }
  const v = state.virtual;
  const link = state.link || 'connecting';
  if (link !== 'connected') {
    return {
      live: false,
      reason: v
        ? 'Connection to the sonographer lost. Hold the probe still and wait.'
        : 'Waiting for the sonographer to connect.',
    };
  }
  if (!v) return { live: false, reason: 'Waiting for the sonographer to guide the probe.' };
  const ageMs = (Number.isFinite(v.age_ms) ? v.age_ms : 0) + (nowMs - v.arrivedMs);
  if (v.clutch) {
    return {
      live: false,
      ageMs,
      reason: 'The sonographer is repositioning their hand. Hold the probe still.',
    };
  }
  if (ageMs > STALE_AFTER_MS) {
    const s = (ageMs / 1000).toFixed(1);
    return {
      live: false,
      ageMs,
      reason: `No update from the sonographer for ${s} s. Hold the probe still.`,
    };
  }
  return { live: true, ageMs, reason: '' };
}

// The HUD's "sonographer" row: the link's state, or how long the sonographer has been silent
// when the guide went stale on a link still called connected (a killed expert's link stays
// "connected" until the transport notices it, a second or more after the poses stop).
export function linkText(state, guide) {
  const link = state.link || 'connecting';
  if (link === 'connected' && guide.ageMs > STALE_AFTER_MS) {
    return `silent for ${(guide.ageMs / 1000).toFixed(1)} s`;
  }
  return link;
}

// The move from the real tip to the virtual one in the patient's words, from the model:
// e.g. "9 mm toward the feet, press it 3 mm deeper".
export function describeMove(probe, virtual, model, minMm = 3) {
  const d = vector(virtual.position).sub(vector(probe.position));
  if (!model) return '';
  d.applyQuaternion(quaternion(model.quaternion).invert()).multiplyScalar(1000);
  const parts = [
    [Math.abs(d.x), d.x > 0 ? 'toward the feet' : 'toward the head'],
    [Math.abs(d.z), d.z > 0 ? "to the patient's right" : "to the patient's left"],
    [Math.abs(d.y), d.y > 0 ? 'lift' : 'press'],
  ]
    .filter(([mm]) => mm >= minMm)
    .sort((a, b) => b[0] - a[0])
    .slice(0, 2);
  return parts
    .map(([mm, words]) =>
      words === 'lift' || words === 'press'
        ? `${words} it ${mm.toFixed(0)} mm ${words === 'press' ? 'deeper' : 'higher'}`
        : `${mm.toFixed(0)} mm ${words}`,
    )
    .join(', ');
}
