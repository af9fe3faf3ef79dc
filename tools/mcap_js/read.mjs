// An MCAP file as Foxglove's own JavaScript library reads it: an independent check of the logger's files
// (tests/test_mcap_js.py, run in CI by .ci/run).
//
//   npm ci --prefix tools/mcap_js && node tools/mcap_js/read.mjs drive.mcap
//
// Prints ONE JSON line: what McapIndexedReader reads through the file's summary and index ("indexed"), and what a
// plain McapStreamReader walk from the first byte reads ("stream"), which is all a file cut short (power cut,
// kill -9) has. Each gives per topic its schema name and encoding and its message encoding, messages per topic,
// the log-time range, the chunk count, how many messages are not JSON, and the samples of /imu/batch (the
// length of each message's t_sync_ns, summed). Times are exact integers (nanoseconds). A file without its end
// (the stream walk did not reach the footer) gives the indexed reader's error as "indexed": {"error": ...};
// any other error is one line on stderr and exit status 1.
//
// Chunks are decompressed with the two WebAssembly packages @mcap/support's loadDecompressHandlers uses for
// zstd and lz4 (the logger writes no bz2): @mcap/support itself would add protobufjs and bz2 for nothing.
import { open } from "node:fs/promises";

import lz4 from "@foxglove/wasm-lz4";
import zstd from "@foxglove/wasm-zstd";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";

const IMU_BATCH = "/imu/batch";
const STREAM_PIECE = 1 << 20; // bytes handed to the stream reader at a time, as a download would

async function decompressHandlers() {
  await Promise.all([zstd.isLoaded, lz4.isLoaded]);
  return {
    zstd: (data, size) => new Uint8Array(zstd.decompress(data, Number(size))),
    lz4: (data, size) => new Uint8Array(lz4(data, Number(size))),
  };
}

// What the messages of one read say; channels and schemas as the reader knows them.
class Tally {
  constructor() {
    this.counts = {};
    this.notJson = 0;
    this.imuBatchSamples = 0;
    this.start = undefined;
    this.end = undefined;
    this.decoder = new TextDecoder("utf-8", { fatal: true });
  }

  add(message, channel) {
    const topic = channel.topic;
    this.counts[topic] = (this.counts[topic] ?? 0) + 1;
    if (this.start === undefined || message.logTime < this.start) this.start = message.logTime;
    if (this.end === undefined || message.logTime > this.end) this.end = message.logTime;
    let body;
    try {
      body = JSON.parse(this.decoder.decode(message.data));
    } catch {
      this.notJson += 1;
      return;
    }
    if (topic === IMU_BATCH) {
      const sync = body?.t_sync_ns;
      if (!Array.isArray(sync)) throw new Error(`an ${IMU_BATCH} message without a t_sync_ns array`);
      this.imuBatchSamples += sync.length;
    }
  }

  result(channels, schemas, chunks) {
    const topics = {};
    for (const channel of channels.values()) {
      const schema = schemas.get(channel.schemaId);
      topics[channel.topic] = {
        schema: schema?.name ?? null,
        schema_encoding: schema?.encoding ?? null,
        message_encoding: channel.messageEncoding,
      };
    }
    return {
      topics,
      counts: this.counts,
      messages: Object.values(this.counts).reduce((a, b) => a + b, 0),
      time_range: this.start === undefined ? null : [this.start, this.end],
      chunks,
      not_json: this.notJson,
      all_json: this.notJson === 0,
      imu_batch_samples: this.imuBatchSamples,
    };
  }
}

async function readIndexed(handle, handlers) {
  const { size } = await handle.stat();
  const readable = {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buf = new Uint8Array(Number(length));
      const { bytesRead } = await handle.read(buf, 0, buf.length, Number(offset));
      if (bytesRead !== buf.length) throw new Error(`short read at byte ${offset}`);
      return buf;
    },
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: handlers });
  const tally = new Tally();
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    tally.add(message, reader.channelsById.get(message.channelId));
  }
  const out = tally.result(reader.channelsById, reader.schemasById, reader.chunkIndexes.length);
  const stats = reader.statistics;
  out.statistics = stats === undefined ? null : {
    messages: stats.messageCount,
    chunks: stats.chunkCount,
    time_range: [stats.messageStartTime, stats.messageEndTime],
  };
  return out;
}

async function readStream(handle, handlers) {
  const reader = new McapStreamReader({ includeChunks: true, decompressHandlers: handlers, validateCrcs: true });
  const channels = new Map();
  const schemas = new Map();
  const tally = new Tally();
  let chunks = 0;
  const piece = new Uint8Array(STREAM_PIECE);
  for (let offset = 0; ;) {
    const { bytesRead } = await handle.read(piece, 0, piece.length, offset);
    if (bytesRead === 0) break;
    offset += bytesRead;
    reader.append(piece.subarray(0, bytesRead));
    for (let record; (record = reader.nextRecord()) !== undefined;) {
      if (record.type === "Schema") schemas.set(record.id, record);
      else if (record.type === "Channel") channels.set(record.id, record);
      else if (record.type === "Chunk") chunks += 1;
      else if (record.type === "Message") tally.add(record, channels.get(record.channelId));
    }
    if (reader.done()) break;
  }
  const out = tally.result(channels, schemas, chunks);
  out.complete = reader.done();
  out.bytes_unread = reader.done() ? 0 : reader.bytesRemaining();
  return out;
}

function toJson(value) {
  // BigInt times as exact JSON integers (JSON.stringify refuses BigInt, and a Number would round them).
  const text = JSON.stringify(value, (_key, v) => (typeof v === "bigint" ? `@bigint:${v}` : v));
  return text.replace(/"@bigint:(-?\d+)"/g, "$1");
}

async function main(argv) {
  if (argv.length !== 1) throw new Error("usage: node read.mjs FILE.mcap");
  const handle = await open(argv[0], "r");
  try {
    const handlers = await decompressHandlers();
    const stream = await readStream(handle, handlers);
    let indexed;
    try {
      indexed = await readIndexed(handle, handlers);
    } catch (err) {
      if (stream.complete) throw err; // a whole file must read through its index
      indexed = { error: String(err?.message ?? err).split("\n")[0] };
    }
    process.stdout.write(`${toJson({ file: argv[0], indexed, stream })}\n`);
  } finally {
    await handle.close();
  }
}

main(process.argv.slice(2)).catch((err) => {
  process.stderr.write(`read.mjs: ${String(err?.message ?? err).split("\n")[0]}\n`);
  process.exit(1);
});
