"""FocusTrack's shared core: the domain vocabulary, geometry, timing and the wire contract.

`domain` (flags, z-ranges, acquisitions, measurements, maps), `geometry`, `timing`,
`maps` (map files), `surfaces` (true focus surfaces, simulated measurement noise), `fusion`
(extended depth of field), `settings` (a service's options), `rest` (the estimator API's
models to and from the domain), `serving` (the HTTP edge), `health`, and the Zenoh edge
(`wire`, generated `v1`). Depends on no service.
"""
