"""Scene input, the lowest layer: the photos' cameras (camera, colmap), the proxy polygons (proxy),
checked file and image input/output (files), and a whole scene folder loaded and checked (loading).

Imports nothing from the layers above (geometry, sampling, method, ...); tests/test_layers.py checks it."""
