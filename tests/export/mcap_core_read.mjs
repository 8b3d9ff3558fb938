// Read an exported file with Foxglove's own MCAP reader (@mcap/core), zstd via fzstd.
import { McapIndexedReader } from "@mcap/core";
import { decompress } from "fzstd";
import { open } from "node:fs/promises";
const path = process.argv[2];
const fh = await open(path, "r");
const size = (await fh.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buf = new Uint8Array(Number(length));
    await fh.read(buf, 0, Number(length), Number(offset));
    return buf;
  },
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: { zstd: (data, size) => decompress(data, new Uint8Array(Number(size))) },
});
const counts = {};
let firstVideo = null, keyframes = 0, bytes = 0;
for await (const msg of reader.readMessages()) {
  const ch = reader.channelsById.get(msg.channelId);
  const schema = reader.schemasById.get(ch.schemaId);
  counts[`${ch.topic} (${schema.name})`] = (counts[`${ch.topic} (${schema.name})`] ?? 0) + 1;
  if (schema.name === "foxglove.CompressedVideo") {
    const m = JSON.parse(new TextDecoder().decode(msg.data));
    const data = Buffer.from(m.data, "base64");
    bytes += data.length;
    // an IDR NAL (type 5) with an SPS (type 7) before it: a keyframe message Foxglove can start at
    let sps = false, idr = false;
    for (let i = 0; i + 3 < data.length; i++) {
      if (data[i] === 0 && data[i + 1] === 0 && data[i + 2] === 1) {
        const t = data[i + 3] & 0x1f; if (t === 7) sps = true; if (t === 5) idr = true;
      }
    }
    if (idr && sps) keyframes++;
    if (!firstVideo) firstVideo = { topic: ch.topic, format: m.format, logTime: msg.logTime, sps, idr };
  }
}
console.log(JSON.stringify({ profile: reader.header.profile, library: reader.header.library,
  messageCount: Number(reader.statistics.messageCount), counts, firstVideo: { ...firstVideo, logTime: String(firstVideo.logTime) },
  videoKeyframesWithSps: keyframes, videoBytes: bytes }, null, 1));
