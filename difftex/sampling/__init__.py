"""Photo sampling, shared by the method, the baselines and the peers: photos mapped into a polygon's
texel frame at a level's resolution (texels: the texel -> pixel maps and levels; photos: the decoded
photos of one polygon and their sampled colours), and colour spaces with brightness transfers (colour).

Imports only the scene and geometry layers."""
