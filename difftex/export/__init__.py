"""Model export: the per-polygon textures packed into atlases and written as a textured OBJ and GLB,
rendered back into a photo's view (assemble); polygon outlines drawn over a photo (overlay)."""
