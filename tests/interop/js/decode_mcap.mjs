// Decode every ROS 2 (cdr) channel of an MCAP file with Foxglove's own readers, as Foxglove does:
// @mcap/core's McapIndexedReader (zstd chunks through fzstd), @foxglove/rosmsg's parser (ros2: true)
// on the channel's ros2msg schema, and @foxglove/rosmsg2-serialization's MessageReader.
//
//   node decode_mcap.mjs FILE.mcap
//
// Prints one JSON object: {topics: {topic: {count, decoded, trailing, schema, schema_encoding,
// message_encoding, first, last}}, errors: [...]}. `trailing` counts messages the reader finished
// before their last byte (a schema that does not match the payload). Exit status 1 on any error.
import { open } from "node:fs/promises";

import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { McapIndexedReader } from "@mcap/core";
import { decompress } from "fzstd";

const path = process.argv[2];
if (!path) {
  console.error("usage: node decode_mcap.mjs FILE.mcap");
  process.exit(2);
}

const handle = await open(path, "r");
const size = (await handle.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buf = new Uint8Array(Number(length));
    await handle.read(buf, 0, Number(length), Number(offset));
    return buf;
  },
};
const decompressHandlers = {
  zstd: (buffer, decompressedSize) => decompress(buffer, new Uint8Array(Number(decompressedSize))),
};

const json = (value) => JSON.stringify(value, (_k, v) => (typeof v === "bigint" ? v.toString() : v));
const out = { topics: {}, errors: [] };
try {
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const readers = new Map();
  for (const channel of reader.channelsById.values()) {
    if (channel.messageEncoding !== "cdr") continue;
    const schema = reader.schemasById.get(channel.schemaId);
    try {
      const definitions = parse(new TextDecoder().decode(schema.data), { ros2: true });
      readers.set(channel.id, new MessageReader(definitions));
    } catch (err) {
      out.errors.push(`${channel.topic}: schema ${schema.name}: ${err}`);
    }
    out.topics[channel.topic] = {
      count: 0, decoded: 0, trailing: 0, schema: schema.name, schema_encoding: schema.encoding,
      message_encoding: channel.messageEncoding, first: null, last: null,
    };
  }
  for await (const message of reader.readMessages()) {
    const msgReader = readers.get(message.channelId);
    const topic = reader.channelsById.get(message.channelId).topic;
    if (!(topic in out.topics)) continue;
    const entry = out.topics[topic];
    entry.count += 1;
    if (!msgReader) continue;
    try {
      const decoded = msgReader.readMessage(message.data);
      entry.decoded += 1;
      if (msgReader.lastReadHadTrailingBytes()) entry.trailing += 1;
      entry.first ??= decoded;
      entry.last = decoded;
    } catch (err) {
      out.errors.push(`${topic}: message at ${message.logTime}: ${err}`);
    }
  }
} catch (err) {
  out.errors.push(`${path}: ${err}`);
} finally {
  await handle.close();
}
// exitCode, not process.exit(): stdout to a pipe is written asynchronously, and exit() would cut
// the JSON off at the pipe's buffer (128 kB) now that the recording holds large sensor messages.
console.log(json(out));
process.exitCode = out.errors.length ? 1 : 0;
