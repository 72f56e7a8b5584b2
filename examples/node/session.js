// An esa-server session from Node.js with @grpc/grpc-js and @grpc/proto-loader: create a
// session, then per step Probe -> evaluate the critic at the probe -> Report, end the
// episode, close the session. The proto is loaded at run time from proto/esa/v1/esa.proto.
// Needs Node.js 18 or newer and an esa-server: a running one, or a build of this checkout
// (`cargo build --release -p esa-server`); no Python.
//
//   npm ci && node session.js                  # spawns ESA_SERVER_BIN or target/release/esa-server
//   node session.js 127.0.0.1:50051            # or talks to a running server
//
// Exits 0 when ESA moved the action toward the critic's best (0.7) and every call succeeded.
"use strict";

const path = require("node:path");
const fs = require("node:fs");
const readline = require("node:readline");
const { spawn } = require("node:child_process");
const grpc = require("@grpc/grpc-js");
const protoLoader = require("@grpc/proto-loader");

const ROOT = path.resolve(__dirname, "..", "..");
const PROTO = path.join(ROOT, "proto", "esa", "v1", "esa.proto");
const BEST = 0.7;

function serverBinary() {
  if (process.env.ESA_SERVER_BIN) return process.env.ESA_SERVER_BIN;
  for (const profile of ["release", "debug"]) {
    const candidate = path.join(ROOT, "target", profile, "esa-server");
    if (fs.existsSync(candidate)) return candidate;
  }
  throw new Error("no esa-server: set ESA_SERVER_BIN or run `cargo build --release -p esa-server`");
}

// Starts esa-server on a free port; resolves with [child, "127.0.0.1:port"].
function spawnServer() {
  const child = spawn(serverBinary(), ["--listen", "127.0.0.1:0", "--parent-pid", String(process.pid)], {
    stdio: ["ignore", "pipe", "inherit"],
  });
  return new Promise((resolve, reject) => {
    const lines = readline.createInterface({ input: child.stdout });
    lines.on("line", (line) => {
      const match = /^listening on (\S+)/.exec(line);
      if (match) resolve([child, match[1]]);
    });
    child.on("exit", (code) => reject(new Error(`esa-server exited (${code}) before listening`)));
  });
}

// A unary call as a promise, with a 10 s deadline; a failure carries the gRPC status code.
function call(client, method, request) {
  const deadline = new Date(Date.now() + 10_000);
  return new Promise((resolve, reject) => {
    client[method](request, { deadline }, (err, response) => (err ? reject(err) : resolve(response)));
  });
}

async function run(address) {
  const definition = protoLoader.loadSync(PROTO, { keepCase: true, longs: Number, defaults: true });
  const esa = grpc.loadPackageDefinition(definition).esa.v1;
  const client = new esa.EsaService(address, grpc.credentials.createInsecure());

  const config = {
    action_dim: 1,
    dt: 0.04,
    amplitude: [0.2],
    frequency: [31.4],
    learning_rate: [0.5],
    action_low: [-1.0],
    action_high: [1.0],
  };
  const { session_id } = await call(client, "CreateSession", { session_id: "", config });
  const critic = (a) => -(a - BEST) * (a - BEST);
  let applied = 0;
  for (let step = 0; step < 200; step++) {
    // The policy always says 0.0; ESA probes around it and shifts it.
    const probe = await call(client, "Probe", {
      session_id,
      step,
      action: [0.0],
      episode_start: step === 0,
    });
    const report = await call(client, "Report", { session_id, step, q_value: critic(probe.probe[0]) });
    applied = report.action[0];
  }
  const { episodes_completed } = await call(client, "EndEpisode", { session_id });
  try {
    await call(client, "Report", { session_id: "nobody", step: 0, q_value: 0 });
    throw new Error("a report for an unknown session succeeded");
  } catch (err) {
    if (err.code !== grpc.status.NOT_FOUND) throw err;
  }
  await call(client, "CloseSession", { session_id });
  client.close();
  console.log(
    `session ${session_id}: the policy says 0.0, the critic's best is ${BEST}; ` +
      `ESA's improved action after 200 steps: ${applied.toFixed(3)} (episodes completed: ${episodes_completed})`,
  );
  if (!(applied > 0.2)) throw new Error(`ESA did not move the action toward ${BEST}: ${applied}`);
}

async function main() {
  let child = null;
  let address = process.argv[2];
  if (!address) [child, address] = await spawnServer();
  try {
    await run(address);
  } finally {
    if (child) child.kill();
  }
}

main().catch((err) => {
  console.error(err);
  process.exit(1);
});
