// An independent OPC UA client (node-opcua) for the simulated CNC's server tests.
//
//   node opcua_client.mjs <endpoint> <operations-json> [--pki <folder>] [--namespace <uri>]
//
// operations: a JSON list, run in order, node ids are strings in <namespace>:
//   [{"read": "Spindle.ActualSpeed"}, {"write": "Macro.501", "value": 0.5}]
// A write sends an OPC UA Double. The PKI folder (--pki, else $OPCUA_PKI_DIR, else a
// fresh temporary folder) holds the client's certificate store: keep it in the test's
// temporary folder so no test writes to the home directory.
//
// Prints one JSON object on stdout:
//   {"namespaceIndex": 2, "results": [
//     {"op": "read", "nodeId": "...", "status": "Good", "dataType": "Double", "value": 4000},
//     {"op": "write", "nodeId": "...", "status": "Good"}]}
// Status codes are names ("Good", "BadTypeMismatch"); a non-finite value is a string
// ("NaN"). Exit status: 0 when connected (whatever the operation statuses), 1 on a
// connection or session failure, 2 on bad arguments.

import {
    AttributeIds,
    DataType,
    MessageSecurityMode,
    OPCUAClient,
    SecurityPolicy,
} from "node-opcua-client";
import { certificateStore, closeQuietly, parseOperations, readOperation, runOperations } from "./common.mjs";

// node-opcua logs (warnings, "Creating default certificate") through console.log:
// send them to stderr so stdout carries nothing but the one JSON object.
console.log = console.error;

const DEFAULT_NAMESPACE = "urn:spindle-gateway:simulated-cnc";

function usage(message) {
    process.stderr.write(`${message}\nusage: node opcua_client.mjs <endpoint> <operations-json> [--pki <folder>] [--namespace <uri>]\n`);
    process.exit(2);
}

function parseArgs(argv) {
    const positional = [];
    const options = { pki: process.env.OPCUA_PKI_DIR, namespace: DEFAULT_NAMESPACE };
    for (let i = 0; i < argv.length; i++) {
        if (argv[i] === "--pki" || argv[i] === "--namespace") {
            if (i + 1 >= argv.length) usage(`${argv[i]} needs a value`);
            options[argv[i].slice(2)] = argv[++i];
        } else {
            positional.push(argv[i]);
        }
    }
    if (positional.length !== 2) usage("expected an endpoint and a JSON list of operations");
    const operations = parseOperations(positional[1], usage);
    return { endpoint: positional[0], operations, ...options };
}

function jsonValue(value) {
    return typeof value === "number" && !Number.isFinite(value) ? String(value) : value;
}

async function run(session, namespaceIndex, op) {
    if (typeof op.read === "string") return readOperation(session, namespaceIndex, op.read, jsonValue);
    if (typeof op.write === "string" && typeof op.value === "number") {
        const nodeId = `ns=${namespaceIndex};s=${op.write}`;
        const status = await session.write({
            nodeId,
            attributeId: AttributeIds.Value,
            value: { value: { dataType: DataType.Double, value: op.value } },
        });
        return { op: "write", nodeId: op.write, status: status.name };
    }
    return { op: "invalid", operation: op, status: "BadInvalidArgument" };
}

async function main() {
    const args = parseArgs(process.argv.slice(2));
    const { manager: certificateManager } = certificateStore(args.pki);
    const client = OPCUAClient.create({
        applicationName: "spindle-gateway-node-test-client",
        securityMode: MessageSecurityMode.None,
        securityPolicy: SecurityPolicy.None,
        clientCertificateManager: certificateManager,
        endpointMustExist: false,
        connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 500 },
    });

    let session;
    try {
        await client.connect(args.endpoint);
        session = await client.createSession();
    } catch (err) {
        process.stderr.write(`cannot connect to ${args.endpoint}: ${err.message}\n`);
        await client.disconnect().catch(() => {});
        process.exit(1);
    }

    try {
        const { namespaceIndex, results } = await runOperations(session, args.namespace, args.operations, run);
        process.stdout.write(`${JSON.stringify({ namespaceIndex, results })}\n`);
    } catch (err) {
        process.stderr.write(`session failure: ${err.message}\n`);
        process.exitCode = 1;
    } finally {
        await closeQuietly(session, client);
    }
}

await main();
