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

import { mkdtempSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { OPCUACertificateManager } from "node-opcua-certificate-manager";
import {
    AttributeIds,
    DataType,
    MessageSecurityMode,
    OPCUAClient,
    SecurityPolicy,
} from "node-opcua-client";

// node-opcua logs (warnings, "Creating default certificate") through console.log:
// send them to stderr so stdout carries nothing but the one JSON object.
console.log = console.error;

const DEFAULT_NAMESPACE = "urn:spindle-gateway:simulated-cnc";
const NAMESPACE_ARRAY = "ns=0;i=2255";

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
    let operations;
    try {
        operations = JSON.parse(positional[1]);
    } catch (err) {
        usage(`operations are not JSON: ${err.message}`);
    }
    if (!Array.isArray(operations)) usage("operations must be a JSON list");
    return { endpoint: positional[0], operations, ...options };
}

function jsonValue(value) {
    return typeof value === "number" && !Number.isFinite(value) ? String(value) : value;
}

async function run(session, namespaceIndex, op) {
    if (typeof op.read === "string") {
        const nodeId = `ns=${namespaceIndex};s=${op.read}`;
        const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
        return {
            op: "read",
            nodeId: op.read,
            status: dv.statusCode.name,
            dataType: DataType[dv.value.dataType],
            value: jsonValue(dv.value.value),
        };
    }
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
    const rootFolder = args.pki ?? mkdtempSync(path.join(tmpdir(), "opcua-pki-"));
    const certificateManager = new OPCUACertificateManager({
        rootFolder,
        automaticallyAcceptUnknownCertificate: true,
    });
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
        const namespaces = (await session.read({ nodeId: NAMESPACE_ARRAY, attributeId: AttributeIds.Value })).value.value;
        const namespaceIndex = namespaces.indexOf(args.namespace);
        if (namespaceIndex < 0) throw new Error(`namespace ${args.namespace} not served`);
        const results = [];
        for (const op of args.operations) results.push(await run(session, namespaceIndex, op));
        process.stdout.write(`${JSON.stringify({ namespaceIndex, results })}\n`);
    } catch (err) {
        process.stderr.write(`session failure: ${err.message}\n`);
        process.exitCode = 1;
    } finally {
        await session.close().catch(() => {});
        await client.disconnect().catch(() => {});
    }
}

await main();
