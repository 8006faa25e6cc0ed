"""Protocol drivers (Modbus RTU/TCP, OPC UA): connect, read, write, report link health.

Drivers know protocols and nothing about thermal error.
"""
