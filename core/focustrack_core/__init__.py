"""FocusTrack's shared core: the domain vocabulary, geometry, timing and the wire contract.

`domain` (flags, z-ranges, acquisitions, measurements, maps), `geometry`, `timing`,
`maps` (map files), `config`, `health`, and the Zenoh edge (`wire`, generated `v1`).
Depends on no service.
"""
