// Decode MCAP files the way Foxglove does: @mcap/core (indexed and stream readers) for the records,
// @foxglove/rosmsg to parse each channel's ros2msg schema, @foxglove/rosmsg2-serialization to decode
// every message. Prints one JSON object: per file, what each reader saw (used by
// test/test_interop_foxglove.py, which compares it with `der replay info` and metadata.yaml).
//
//   node decode_bags.js FILE.mcap [FILE.mcap ...]
"use strict";

const fs = require("node:fs/promises");
const { McapIndexedReader, McapStreamReader } = require("@mcap/core");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");

const NS = 1000000000n;

function stampNs(msg) {
  const h = msg && msg.header;
  if (!h || !h.stamp) return null;
  return BigInt(h.stamp.sec) * NS + BigInt(h.stamp.nanosec);
}

// What one reader saw: counts, decode failures, header stamps going back, log times, the tf frames.
class Tally {
  constructor() {
    this.readers = new Map(); // channel id -> MessageReader
    this.topics = {};
  }
  channel(channel, schema) {
    if (schema.encoding !== "ros2msg" || channel.messageEncoding !== "cdr") {
      throw new Error(`${channel.topic}: schema ${schema.encoding} / messages ${channel.messageEncoding}`);
    }
    const text = new TextDecoder().decode(schema.data);
    this.readers.set(channel.id, { topic: channel.topic, reader: new MessageReader(parse(text, { ros2: true })) });
  }
  message(channelId, logTime, data) {
    const entry = this.readers.get(channelId);
    const t = (this.topics[entry.topic] ??= {
      count: 0, failures: 0, stamps_back: 0, last_stamp: null, log_time_min: null, log_time_max: null, frames: [],
    });
    t.count += 1;
    if (t.log_time_min === null || logTime < t.log_time_min) t.log_time_min = logTime;
    if (t.log_time_max === null || logTime > t.log_time_max) t.log_time_max = logTime;
    let msg;
    try {
      msg = entry.reader.readMessage(data);
    } catch (err) {
      t.failures += 1;
      return;
    }
    const stamp = stampNs(msg);
    if (stamp !== null) {
      if (t.last_stamp !== null && stamp < t.last_stamp) t.stamps_back += 1;
      t.last_stamp = stamp;
    }
    if (msg.transforms) {
      for (const tr of msg.transforms) {
        const pair = `${tr.header.frame_id}->${tr.child_frame_id}`;
        if (!t.frames.includes(pair)) t.frames.push(pair);
      }
    }
  }
  result() {
    const out = {};
    for (const [topic, t] of Object.entries(this.topics)) {
      out[topic] = {
        count: t.count, failures: t.failures, stamps_back: t.stamps_back, frames: t.frames,
        log_time_min: t.log_time_min === null ? null : t.log_time_min.toString(),
        log_time_max: t.log_time_max === null ? null : t.log_time_max.toString(),
      };
    }
    return out;
  }
}

async function indexed(path) {
  const handle = await fs.open(path, "r");
  try {
    const readable = {
      size: async () => BigInt((await handle.stat()).size),
      read: async (offset, length) => {
        const buf = new Uint8Array(Number(length));
        await handle.read(buf, 0, Number(length), Number(offset));
        return buf;
      },
    };
    const reader = await McapIndexedReader.Initialize({ readable });
    const tally = new Tally();
    for (const channel of reader.channelsById.values()) {
      tally.channel(channel, reader.schemasById.get(channel.schemaId));
    }
    for await (const m of reader.readMessages()) tally.message(m.channelId, m.logTime, m.data);
    return tally.result();
  } finally {
    await handle.close();
  }
}

async function stream(path) {
  const reader = new McapStreamReader({ validateCrcs: true });
  reader.append(await fs.readFile(path));
  const tally = new Tally();
  const schemas = new Map();
  let record;
  while ((record = reader.nextRecord()) !== undefined) {
    if (record.type === "Schema") schemas.set(record.id, record);
    else if (record.type === "Channel") tally.channel(record, schemas.get(record.schemaId));
    else if (record.type === "Message") tally.message(record.channelId, record.logTime, record.data);
  }
  if (!reader.done()) throw new Error(`${path}: the stream reader did not reach the end of the file`);
  return tally.result();
}

async function main() {
  const files = process.argv.slice(2);
  if (files.length === 0) {
    console.error("usage: node decode_bags.js FILE.mcap [...]");
    process.exit(2);
  }
  const out = {};
  for (const f of files) out[f] = { indexed: await indexed(f), stream: await stream(f) };
  console.log(JSON.stringify(out));
}

main().catch((err) => {
  console.error(err && err.stack ? err.stack : String(err));
  process.exit(1);
});
