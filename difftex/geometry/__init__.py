"""Geometry: each polygon's texture frame and the photo <-> texel mapping (frames), ideal pinhole
cameras (pinhole), the proxy as a triangle mesh (meshing), ray casting against the proxy (raycast),
per-photo visibility masks (visibility), texel density (density), and the photo filter stage
(photo_filter), which decides from sharpness and viewing geometry which photos see which polygon.

Imports only the scene layer (and errors, config)."""
