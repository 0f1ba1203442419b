"""The peer programs (texrecon, MeshLab per-face, MeshLab per-texel blend, reprojection) as rows of the tables.

A peer textures the same scene from the same photos as the other methods: the photos the shared
filter kept (``OUT/common/photos.json``), into the frames of the shared visibility files (so its
maps have the table's resolution and are scored on the same texels), through
:func:`difftex.evaluation.peers.run.run_peer`; its results folder is then scored by ``difftex evaluate`` like
every other. A peer that is not installed gives a row that says so instead of figures.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from difftex.evaluation.peers.run import LABELS, PEERS  # noqa: E402

__all__ = ["PEERS", "LABELS", "is_peer", "unavailable", "run_peer", "missing_line"]


def is_peer(method: str) -> bool:
    return method in PEERS


def unavailable(method: str, scene: Path | None = None) -> str:
    """Why the peer cannot run here ('' when it can); reprojection also needs the scene's dense mesh."""
    from difftex.evaluation.peers import meshlab, reprojection, texrecon

    if method == "reprojection":
        return reprojection.unavailable_reason(scene)
    return (texrecon if method == "texrecon" else meshlab).unavailable_reason()


def run_peer(method: str, scene: Path, r: Path, common: dict, **cfg) -> dict:
    """Run one peer into results folder ``r`` on the shared photos and frames.

    Returns the shape of ``evaluation.common.run_method`` ({"method", "results", "total_s", ...})
    plus the peer's figures: ``prepare_s``, ``peer_s``, ``import_s`` (wall), ``peer_cpu_s``,
    ``peer_peak_rss_mib``, ``prepare_cpu_s``, ``import_cpu_s`` and the whole ``peer.json`` record.
    When the peer is not installed: {"method", "results": None, "missing": reason}.
    """
    from difftex.evaluation.peers.run import PeerConfig
    from difftex.evaluation.peers.run import run_peer as run

    why = unavailable(method, scene)
    if why:
        return {"method": method, "results": None, "missing": why}
    t0 = time.perf_counter()
    rec = run(method, scene, r, PeerConfig(**cfg), visibility=common["visibility"],
              polygons=[row["id"] for row in common["polygons"]],
              photos_table=Path(common["config"]).parent / "photos.json")
    return {
        "method": method,
        "results": str(r),
        "total_s": time.perf_counter() - t0,
        "prepare_s": rec["prepare"]["wall_s"],
        "peer_s": rec["peer"]["wall_s"],
        "import_s": rec["import"]["wall_s"],
        "prepare_cpu_s": rec["prepare"]["cpu_s"],
        "peer_cpu_s": rec["peer"]["cpu_s"],
        "import_cpu_s": rec["import"]["cpu_s"],
        "peer_peak_rss_mib": rec["peer"]["peak_rss_mib"],
        "peer_record": rec,
    }


def missing_line(label: str, reason: str, columns: int, first: list[str] | None = None) -> str:
    """A markdown table row for a peer that did not run: its label, then the reason across the figures."""
    cells = (first or []) + [label, f"not run: {reason}"] + ["n/a"] * (columns - len(first or []) - 2)
    return "| " + " | ".join(cells) + " |"


def timing_note(rows: list[dict]) -> str | None:
    """One line for the notes: what a peer's time covers, with each peer's split."""
    runs = [r["run"] for r in rows if r.get("run") and r["run"].get("peer_s") is not None]
    if not runs:
        return None
    parts = [f"{LABELS[r['method']]} {r['prepare_s']:.0f} + {r['peer_s']:.0f} + {r['import_s']:.0f} s" for r in runs]
    return (
        "Peers' time = difftex's preparation (photos resampled as centred pinhole cameras, proxy meshed) + the "
        "program + import into the UV frames (wall seconds; CPU and peak memory per phase in the JSON): "
        + ", ".join(parts)
        + "."
    )
