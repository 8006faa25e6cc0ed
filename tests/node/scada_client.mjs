// An independent OPC UA client (node-opcua) for the gateway's secured SCADA server tests.
//
//   node scada_client.mjs <endpoint> <operations-json> [--pki <folder>] [--namespace <uri>]
//        [--user <name> --password <secret>] [--anonymous] [--mode SignAndEncrypt|None]
//
// Connects with Basic256Sha256 + SignAndEncrypt (or with no security at all when
// --mode None, to show that the server refuses it), opens a session with the user
// name and password (the password may also come from $SCADA_PASSWORD) or, with
// --anonymous, an anonymous one, then runs the operations in order. Node ids are
// strings in <namespace> (default urn:spindle-gateway:scada):
//   [{"read": "vmc-1.SpeedRpm"}, {"write": "vmc-1.CompensationEnabled", "value": false}]
// A JSON boolean is written as an OPC UA Boolean, a number as a Double.
//
// Prints one JSON object on stdout:
//   {"namespaceIndex": 2, "certificate": "<pki>/own/certs/client_certificate.pem",
//    "results": [{"op": "read", "nodeId": "...", "status": "Good", "dataType": "Double", "value": 41.5},
//                {"op": "write", "nodeId": "...", "status": "BadUserAccessDenied"}]}
// Status codes are names; a write refused as a whole request (a ServiceFault) reports
// the fault's status. A non-finite number is a string ("NaN"), a null value null.
// Exit status: 0 when a session was opened (whatever the operation statuses); 1 on a
// connection or session failure, with {"error": "<message>", "status": "<StatusCode
// name or null>", "certificate": ...} on stdout; 2 on bad arguments.

import path from "node:path";
import {
    AttributeIds,
    DataType,
    MessageSecurityMode,
    OPCUAClient,
    SecurityPolicy,
    UserTokenType,
} from "node-opcua-client";
import { certificateStore, closeQuietly, parseOperations, readOperation, runOperations } from "./common.mjs";

// node-opcua logs through console.log: keep stdout for the one JSON object.
console.log = console.error;

const DEFAULT_NAMESPACE = "urn:spindle-gateway:scada";
const USAGE =
    "usage: node scada_client.mjs <endpoint> <operations-json> [--pki <folder>] [--namespace <uri>] " +
    "[--user <name> --password <secret>] [--anonymous] [--mode SignAndEncrypt|None]";

function usage(message) {
    process.stderr.write(`${message}\n${USAGE}\n`);
    process.exit(2);
}

function parseArgs(argv) {
    const positional = [];
    const options = {
        pki: process.env.OPCUA_PKI_DIR,
        namespace: DEFAULT_NAMESPACE,
        user: undefined,
        password: process.env.SCADA_PASSWORD,
        anonymous: false,
        mode: "SignAndEncrypt",
    };
    const valued = new Set(["--pki", "--namespace", "--user", "--password", "--mode"]);
    for (let i = 0; i < argv.length; i++) {
        if (valued.has(argv[i])) {
            if (i + 1 >= argv.length) usage(`${argv[i]} needs a value`);
            options[argv[i].slice(2)] = argv[++i];
        } else if (argv[i] === "--anonymous") {
            options.anonymous = true;
        } else {
            positional.push(argv[i]);
        }
    }
    if (positional.length !== 2) usage("expected an endpoint and a JSON list of operations");
    if (!["SignAndEncrypt", "None"].includes(options.mode)) usage(`unknown mode ${options.mode}`);
    if (options.anonymous === (options.user !== undefined)) usage("give either --user or --anonymous");
    if (options.user !== undefined && options.password === undefined) usage("--user needs --password");
    const operations = parseOperations(positional[1], usage);
    return { endpoint: positional[0], operations, ...options };
}

function jsonValue(value) {
    if (value === undefined) return null;
    return typeof value === "number" && !Number.isFinite(value) ? String(value) : value;
}

// The StatusCode name behind an error: a ServiceFault keeps its response on the error,
// other failures only mention it in the message.
function statusOf(err) {
    const name = err?.response?.responseHeader?.serviceResult?.name;
    if (name) return name;
    const match = /\b(Bad[A-Za-z]+)\b/.exec(err?.message ?? "");
    return match ? match[1] : null;
}

async function run(session, namespaceIndex, op) {
    if (typeof op.read === "string") return readOperation(session, namespaceIndex, op.read, jsonValue);
    if (typeof op.write === "string" && ["boolean", "number"].includes(typeof op.value)) {
        const nodeId = `ns=${namespaceIndex};s=${op.write}`;
        const dataType = typeof op.value === "boolean" ? DataType.Boolean : DataType.Double;
        try {
            const status = await session.write({
                nodeId,
                attributeId: AttributeIds.Value,
                value: { value: { dataType, value: op.value } },
            });
            return { op: "write", nodeId: op.write, status: status.name };
        } catch (err) {
            return { op: "write", nodeId: op.write, status: statusOf(err) ?? "Bad", error: err.message };
        }
    }
    return { op: "invalid", operation: op, status: "BadInvalidArgument" };
}

async function main() {
    const args = parseArgs(process.argv.slice(2));
    const { rootFolder, manager: certificateManager } = certificateStore(args.pki);
    const secure = args.mode === "SignAndEncrypt";
    const client = OPCUAClient.create({
        applicationName: "spindle-gateway-scada-test-client",
        securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
        securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
        clientCertificateManager: certificateManager,
        // The client looks the endpoint up first: a mode the server does not offer fails.
        endpointMustExist: true,
        connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 500 },
    });
    const certificate = path.join(rootFolder, "own", "certs", "client_certificate.pem");
    const identity = args.anonymous
        ? { type: UserTokenType.Anonymous }
        : { type: UserTokenType.UserName, userName: args.user, password: args.password };

    let session;
    try {
        await client.connect(args.endpoint);
        session = await client.createSession(identity);
    } catch (err) {
        process.stdout.write(`${JSON.stringify({ error: err.message, status: statusOf(err), certificate })}\n`);
        process.stderr.write(`cannot open a session on ${args.endpoint}: ${err.message}\n`);
        await client.disconnect().catch(() => {});
        process.exit(1);
    }

    try {
        const { namespaceIndex, results } = await runOperations(session, args.namespace, args.operations, run);
        process.stdout.write(`${JSON.stringify({ namespaceIndex, certificate, results })}\n`);
    } catch (err) {
        process.stdout.write(`${JSON.stringify({ error: err.message, status: statusOf(err), certificate })}\n`);
        process.stderr.write(`session failure: ${err.message}\n`);
        process.exitCode = 1;
    } finally {
        await closeQuietly(session, client);
    }
}

await main();
