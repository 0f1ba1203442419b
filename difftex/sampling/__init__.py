"""Photo sampling, shared by the method, the baselines and the peers: photos mapped into a polygon's
texel frame at a level's resolution (texels: the texel -> pixel maps and levels; photos: the decoded
photos of one polygon and their sampled colours), and colour spaces with brightness transfers (colour).

Imports only the scene and geometry layers."""

# Photo samples per texel side at a polygon's own resolution (PhotoSet.supersample). One trilinear
# sample blurs a texel over about twice its width; 2 x 2 sub-samples halve the excess. Measured
# with every method's own sampling switched (evaluation/table1.py, table2.py --optimize
# '{"supersample": 1}'): archive at `fast`, difftex SSIM 0.5268 -> 0.5307 and ST-LPIPS
# 0.569 -> 0.553 against the 2048-texel ground truth, held-out views SSIM 0.663 -> 0.672;
# the real scenes' held-out SSIM 0.8140 / 0.6559 / 0.7281 -> 0.8152 / 0.6685 / 0.7297, for
# about 12 % more texturing time at `fast`.
SUPERSAMPLE = 2
