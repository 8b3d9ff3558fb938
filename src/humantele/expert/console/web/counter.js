// The frame counter the follower stamps in each frame's top-left corner, read back from a
// canvas the page drew (humantele.video.counter.read_counter, same code): 8 x 4 cells of
// 8 px, cells 0-23 the number's 24 bits (most significant first), 24-31 the low byte of the
// CRC-32 of its 3 bytes. A cell is read from the mean luma of its middle half: below 88 a 0,
// above 168 a 1, anything between (no counter, a smeared one) makes the read fail.

const COLS = 8, ROWS = 4, CELL = 8, LOW = 88, HIGH = 168;

const CRC_TABLE = new Uint32Array(256);
for (let n = 0; n < 256; n++) {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  CRC_TABLE[n] = c >>> 0;
}

function check(value) {
  let c = 0xffffffff;
  for (const b of [(value >> 16) & 255, (value >> 8) & 255, value & 255]) {
    c = CRC_TABLE[(c ^ b) & 255] ^ (c >>> 8);
  }
  return ((c ^ 0xffffffff) >>> 0) & 255;
}

// The counter in the top-left corner of a 2D context drawn at the frame's own size, or null.
export function readCounter(g) {
  const w = COLS * CELL, h = ROWS * CELL;
  if (g.canvas.width < w || g.canvas.height < h) return null;
  const d = g.getImageData(0, 0, w, h).data;
  let value = 0, crc = 0;
  for (let i = 0; i < ROWS * COLS; i++) {
    const r = Math.floor(i / COLS), col = i % COLS;
    let sum = 0, n = 0;
    for (let y = r * CELL + 2; y < r * CELL + 6; y++) {
      for (let x = col * CELL + 2; x < col * CELL + 6; x++) {
        const o = 4 * (y * w + x);
        sum += 0.299 * d[o] + 0.587 * d[o + 1] + 0.114 * d[o + 2];
        n++;
      }
    }
    const m = sum / n;
    if (m > LOW && m < HIGH) return null;
    const bit = m > HIGH ? 1 : 0;
    if (i < 24) value = value * 2 + bit;
    else crc = crc * 2 + bit;
  }
  return crc === check(value) ? value : null;
}
