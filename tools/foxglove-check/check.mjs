// Decode every message of an MCAP file with Foxglove's libraries, as Foxglove Studio does:
// ros2msg schemas through @foxglove/rosmsg, ros2idl schemas (our service events) through
// @foxglove/ros2idl-parser, CDR through @foxglove/rosmsg2-serialization; chunks read by
// @mcap/core with CRCs checked. Prints one JSON line: messages per topic and schema
// encoding, and the failures; exit 0 only if every message decoded.
//   node tools/foxglove-check/check.mjs bags/<run>/bag_0/bag_0_0.mcap
import { McapIndexedReader } from "@mcap/core";
import { parseRos2idl } from "@foxglove/ros2idl-parser";
import { parse as parseMsg } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { decompress as zstd } from "fzstd";
import lz4 from "lz4js";
import { open } from "node:fs/promises";

const fh = await open(process.argv[2], "r");
const size = (await fh.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const b = Buffer.alloc(Number(length));
    await fh.read(b, 0, Number(length), Number(offset));
    return new Uint8Array(b);
  },
};
const decompressHandlers = {
  zstd: (data) => zstd(data),
  lz4: (data) => new Uint8Array(lz4.decompress(data)),
};
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
const readers = new Map();
const counts = {};
const failures = [];
for await (const m of reader.readMessages({ validateCrcs: true })) {
  const ch = reader.channelsById.get(m.channelId);
  const sc = reader.schemasById.get(ch.schemaId);
  const key = `${sc.encoding} ${ch.topic}`;
  try {
    let r = readers.get(ch.id);
    if (!r) {
      const text = new TextDecoder().decode(sc.data);
      const defs = sc.encoding === "ros2idl" ? parseRos2idl(text) : parseMsg(text, { ros2: true });
      r = new MessageReader(defs);
      readers.set(ch.id, r);
    }
    r.readMessage(m.data);
    counts[key] = (counts[key] ?? 0) + 1;
  } catch (e) {
    if (failures.length < 5) failures.push(`${key}: ${e.message}`);
    counts[`FAILED ${key}`] = (counts[`FAILED ${key}`] ?? 0) + 1;
  }
}
console.log(JSON.stringify({ counts, failures }));
process.exit(Object.keys(counts).some((k) => k.startsWith("FAILED")) ? 1 : 0);
