"""The DiffTex method for one polygon (paper Sec. 4): initialisation Q = Q_a Q_c and top-K slots
(levels), the objective (objective, with the terms in difftex.method.losses), data elimination
(elimination), render-space data (render) and the coarse-to-fine loop (loop)."""
