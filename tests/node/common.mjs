// What the node-opcua test clients (opcua_client.mjs, scada_client.mjs) share: their
// operations argument, the client's certificate store, the namespace lookup and the
// read operation.

import { mkdtempSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { OPCUACertificateManager } from "node-opcua-certificate-manager";
import { AttributeIds, DataType } from "node-opcua-client";

const NAMESPACE_ARRAY = "ns=0;i=2255";

// The operations argument: a JSON list, or usage() (which exits with status 2).
export function parseOperations(text, usage) {
    let operations;
    try {
        operations = JSON.parse(text);
    } catch (err) {
        usage(`operations are not JSON: ${err.message}`);
    }
    if (!Array.isArray(operations)) usage("operations must be a JSON list");
    return operations;
}

// The client's certificate store in <pki> (else a fresh temporary folder), so that no
// test writes to the home directory; the folder and the manager.
export function certificateStore(pki) {
    const rootFolder = pki ?? mkdtempSync(path.join(tmpdir(), "opcua-pki-"));
    const manager = new OPCUACertificateManager({
        rootFolder,
        automaticallyAcceptUnknownCertificate: true,
    });
    return { rootFolder, manager };
}

// The index of namespace <uri> on the server; an error when it is not served.
export async function namespaceIndexOf(session, uri) {
    const namespaces = (await session.read({ nodeId: NAMESPACE_ARRAY, attributeId: AttributeIds.Value })).value.value;
    const index = namespaces.indexOf(uri);
    if (index < 0) throw new Error(`namespace ${uri} not served`);
    return index;
}

// {"read": name}: the value of node <name> in the namespace, its status and data type;
// jsonValue turns the value into what JSON can carry.
export async function readOperation(session, namespaceIndex, name, jsonValue) {
    const nodeId = `ns=${namespaceIndex};s=${name}`;
    const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
    return {
        op: "read",
        nodeId: name,
        status: dv.statusCode.name,
        dataType: DataType[dv.value.dataType],
        value: jsonValue(dv.value.value),
        sourceTimestampMs: dv.sourceTimestamp ? dv.sourceTimestamp.getTime() : null,
    };
}

// The operations run in order by run(session, namespaceIndex, op); the namespace's
// index and every operation's result.
export async function runOperations(session, namespace, operations, run) {
    const namespaceIndex = await namespaceIndexOf(session, namespace);
    const results = [];
    for (const op of operations) results.push(await run(session, namespaceIndex, op));
    return { namespaceIndex, results };
}

// The session and the connection closed, whatever state they are in.
export async function closeQuietly(session, client) {
    await session.close().catch(() => {});
    await client.disconnect().catch(() => {});
}
