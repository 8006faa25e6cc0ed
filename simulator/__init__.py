"""A digital twin of a machining centre's spindle, for tests, the demo and bench set-ups.

Physics (a lumped thermal network), temperature sensors with faults, speed
programmes and hidden effects live here. The machine is reachable only through
the same protocols a plant uses (Modbus transmitters, an OPC UA / Modbus CNC,
served by ``simulator.servers``), so the gateway cannot tell it from hardware.
"""
