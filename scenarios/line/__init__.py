"""The line station (`aimbench station`, issue 36; docs/station-line.md): one process that
serves the operator's and the engineer's web pages (NiceGUI), an OPC UA server for the line's
PLC (asyncua) and an HTTP/JSON endpoint for MES, all triggering the same inspection pipeline
(`scenarios.inspection`), one unit at a time.

Modules, one concern each:

- `engine`: the station's one inspection at a time: trigger, refuse while busy, record, the
  state every front end shows, the alarms of SPC, the audit trail, recovery after a kill.
- `auth`: users and roles from the station file, scrypt password hashes.
- `opcua`: the OPC UA server (the PLC's handshake: PartId, Start, Busy, Done, Error...).
- `web`: the operator and engineer pages and the HTTP/JSON endpoint.
"""
