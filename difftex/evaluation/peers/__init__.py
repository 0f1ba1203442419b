"""Peer texturing programs run on the same inputs and scored by the same code as difftex: the
driver (run), measured subprocesses (measure), texrecon and MeshLab, and any textured OBJ read back
into difftex's polygon frames (objimport)."""
