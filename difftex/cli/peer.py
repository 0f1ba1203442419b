"""difftex peer: texture a scene with texrecon, MeshLab or reprojection (texrecon on the dense mesh, baked) and write
a results folder difftex evaluate scores."""

from __future__ import annotations

NAME = "peer"
HELP = ("texture a scene with a peer program (texrecon, MeshLab per-face or per-texel blend, reprojection: texrecon on "
        "the dense mesh baked onto the proxy) into a results folder")


def add_arguments(p) -> None:
    from difftex.evaluation.peers.run import PEERS

    p.add_argument("--method", required=True, choices=PEERS)
    p.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/, proxy)")
    p.add_argument("--out", required=True, help="results folder (textures/<pid>/, peer.json with timings, work/)")
    p.add_argument("--visibility", help="a 'difftex visibility' folder: use its frames and the polygons photos see")
    p.add_argument("--photos", help="the filter's photos.json: give the peer only the photos it kept")
    p.add_argument("--polygons", help="comma-separated polygon ids to write (default: all)")
    p.add_argument("--config", help="YAML config; section 'texture' sets the maps' size when --visibility is not given")
    p.add_argument("--long-side", type=int, help="texels on each map's long side (overrides texture.long_side)")
    p.add_argument("--density", type=float, help="texels per scene unit (overrides texture.density)")
    p.add_argument("--photo-long-side", type=int, help="resample the photos to this long side (default: full size)")
    p.add_argument(
        "--max-edge", type=float, help="mesh edge bound in scene units (default: 1/20 of the camera distance)"
    )
    p.add_argument("--oversample", type=int, default=2,
                   help="MeshLab atlas texels per map texel along each axis (reprojection: rays per texel)")
    p.add_argument("--threads", type=int, default=0, help="the peer's threads (texrecon); 0: its default")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds before the peer is killed")
    p.add_argument("--keep-inputs", action="store_true", help="keep the resampled photos under OUT/work/photos")
    p.add_argument("--dense-mesh", help="reprojection: the dense mesh (default: the first mesh in SCENE/dense/)")
    p.add_argument("--max-faces", type=int, default=500_000,
                   help="reprojection: decimate the dense mesh to at most this many triangles")
    p.add_argument("--relief", type=float, default=1.0,
                   help="reprojection: the bake sees surfaces within this many scene units of each polygon's plane "
                   "(and a fifth of its shorter side)")


def run(args) -> int:
    from difftex.config import TextureConfig, section
    from difftex.errors import DifftexError
    from difftex.evaluation.peers.run import PeerConfig, run_peer

    tex = section(args.config, "texture", TextureConfig)
    long_side, density = tex.long_side, tex.density  # density wins when set, as in difftex visibility
    if args.long_side is not None:
        long_side, density = args.long_side, None
    if args.density is not None:
        density = args.density
    try:
        cfg = PeerConfig(
            photo_long_side=args.photo_long_side,
            max_edge=args.max_edge,
            oversample=args.oversample,
            threads=args.threads,
            timeout_s=args.timeout,
            keep_inputs=args.keep_inputs,
            dense_mesh=args.dense_mesh,
            max_faces=args.max_faces,
            relief=args.relief,
        )
    except ValueError as exc:
        raise DifftexError(f"difftex peer: {exc}") from None
    polygons = [p for p in args.polygons.split(",") if p] if args.polygons else None
    rec = run_peer(
        args.method,
        args.scene,
        args.out,
        cfg,
        visibility=args.visibility,
        polygons=polygons,
        long_side=long_side,
        density=density,
        photos_table=args.photos,
    )
    cov = rec["polygons"]
    print(
        f"peer {args.method}: {len(cov)} polygons, mean coverage {sum(cov.values()) / max(len(cov), 1):.3f}; "
        f"prepare {rec['prepare']['wall_s']:.1f} s, {rec['peer_program']['program']} {rec['peer']['wall_s']:.1f} s "
        f"({rec['peer']['cpu_s']:.1f} CPU s, {rec['peer']['peak_rss_mib']:.0f} MiB), import "
        f"{rec['import']['wall_s']:.1f} s "
        f"-> {args.out}"
    )
    return 0
