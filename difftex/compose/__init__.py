"""Composition and brightness: per-photo brightness transfers by histogram matching (histmatch),
a texture composed from per-photo weights with hole filling (composite), the per-polygon texturing
stage that runs the method and composes its result (texturing), and the per-polygon output files
(outputs)."""
