// An independent Sparkplug B host application for tests, on Eclipse Tahu's JavaScript
// payload library (sparkplug-payload) and the MQTT client sparkplug-client uses (mqtt).
//
// argv[2]: JSON {url, ca, username, password, group, host}. It publishes its STATE
// (retained, will: offline, both with the connect's timestamp), subscribes to the group, decodes every message, checks the
// sequence numbers of each edge node and prints one JSON line per message:
//   {"event":"message","kind":"DDATA","node":..,"device":..,"seq":..,"gap":false,
//    "qos":..,"retain":..,"metrics":[{"name":..,"sentName":..,"alias":..,"type":..,"value":..,
//    "historical":..}]}  (name: as sent, else the birth's name of the alias; sentName: as sent)
// It reads JSON commands on stdin, one per line:
//   {"op":"rebirth","node":N}          NCMD Node Control/Rebirth
//   {"op":"dcmd","node":N,"device":D,"metrics":[{name|alias,type,value}],"timestamp":T,"seq":S}
//   {"op":"raw","topic":T,"hex":H}     arbitrary bytes (a malformed command)
//   {"op":"rawstate","text":X}         X as its STATE payload, not retained (old or malformed)
//   {"op":"state","online":bool}       its own STATE
//   {"op":"quit"}
import { readFileSync } from "node:fs";
import { createInterface } from "node:readline";
import mqtt from "mqtt";
import sparkplugPayload from "sparkplug-payload";

const spb = sparkplugPayload.get("spBv1.0");
const cfg = JSON.parse(process.argv[2]);
const stateTopic = `spBv1.0/STATE/${cfg.host}`;
const say = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const plain = (v) => (v !== null && typeof v === "object" && typeof v.toNumber === "function" ? v.toNumber() : v);
const stateMessage = (online, timestamp = Date.now()) => JSON.stringify({ online, timestamp });
// Sparkplug 3.0: the online STATE carries the timestamp of the will of the CONNECT before it.
const connectedAt = Date.now();

const nodes = new Map(); // node → {seq, bdSeq, aliases: Map(device → Map(alias → name))}

const client = mqtt.connect(cfg.url, {
  ca: readFileSync(cfg.ca),
  username: cfg.username,
  password: cfg.password,
  clientId: `host-${cfg.host}-${process.pid}`,
  clean: true,
  reconnectPeriod: 200,
  will: { topic: stateTopic, payload: stateMessage(false, connectedAt), qos: 1, retain: true },
});

client.on("connect", () => {
  client.subscribe(`spBv1.0/${cfg.group}/#`, { qos: 1 }, () => {
    client.publish(stateTopic, stateMessage(true, connectedAt), { qos: 1, retain: true }, () => say({ event: "online" }));
  });
});
client.on("error", (err) => say({ event: "error", message: String(err) }));
client.on("close", () => say({ event: "closed" }));

function track(kind, node, device, payload) {
  let n = nodes.get(node);
  if (kind === "NBIRTH") {
    n = { seq: -1, bdSeq: null, aliases: new Map() };
    nodes.set(node, n);
  }
  if (!n) return { gap: true, names: new Map() };
  const seq = payload.seq === undefined || payload.seq === null ? null : plain(payload.seq);
  let gap = false;
  if (kind !== "NDEATH" && seq !== null) {
    gap = kind === "NBIRTH" ? seq !== 0 : seq !== (n.seq + 1) % 256;
    n.seq = seq;
  }
  const key = device ?? "";
  if (kind === "NBIRTH" || kind === "DBIRTH") {
    const names = new Map();
    for (const m of payload.metrics ?? []) names.set(plain(m.alias), m.name);
    n.aliases.set(key, names);
  }
  return { gap, names: n.aliases.get(key) ?? new Map() };
}

client.on("message", (topic, buf, packet) => {
  const parts = topic.split("/");
  if (parts[1] === "STATE") return;
  const [, , kind, node, device] = parts;
  if (kind === "NCMD" || kind === "DCMD") return;
  let payload;
  try {
    payload = spb.decodePayload(new Uint8Array(buf));
  } catch (err) {
    say({ event: "undecodable", topic, message: String(err) });
    return;
  }
  const { gap, names } = track(kind, node, device ?? null, payload);
  const metrics = (payload.metrics ?? []).map((m) => ({
    name: m.name ?? names.get(plain(m.alias)) ?? null,
    sentName: m.name ?? null,
    alias: plain(m.alias),
    type: m.type,
    value: plain(m.value),
    historical: Boolean(m.isHistorical),
    unit: m.properties?.engUnit ? plain(m.properties.engUnit.value) : undefined,
  }));
  say({
    event: "message", kind, node, device: device ?? null,
    seq: payload.seq === undefined ? null : plain(payload.seq),
    timestamp: plain(payload.timestamp), gap, qos: packet.qos, retain: packet.retain, metrics,
  });
});

const rl = createInterface({ input: process.stdin });
rl.on("line", (line) => {
  const cmd = JSON.parse(line);
  if (cmd.op === "quit") {
    client.end(true, () => process.exit(0));
  } else if (cmd.op === "state") {
    client.publish(stateTopic, stateMessage(cmd.online), { qos: 1, retain: true }, () => say({ event: "state-sent", online: cmd.online }));
  } else if (cmd.op === "rawstate") {
    client.publish(stateTopic, cmd.text, { qos: 1, retain: false }, () => say({ event: "state-sent", text: cmd.text }));
  } else if (cmd.op === "raw") {
    client.publish(cmd.topic, Buffer.from(cmd.hex, "hex"), { qos: 1 }, () => say({ event: "sent", op: "raw" }));
  } else if (cmd.op === "rebirth") {
    const payload = { timestamp: Date.now(), metrics: [{ name: "Node Control/Rebirth", type: "Boolean", value: true }] };
    client.publish(`spBv1.0/${cfg.group}/NCMD/${cmd.node}`, Buffer.from(spb.encodePayload(payload)), { qos: 1 }, () => say({ event: "sent", op: "rebirth" }));
  } else if (cmd.op === "dcmd") {
    const payload = { timestamp: cmd.timestamp ?? Date.now(), metrics: cmd.metrics };
    if (cmd.seq !== undefined) payload.seq = cmd.seq;
    client.publish(`spBv1.0/${cfg.group}/DCMD/${cmd.node}/${cmd.device}`, Buffer.from(spb.encodePayload(payload)), { qos: 1 }, () => say({ event: "sent", op: "dcmd" }));
  }
});
