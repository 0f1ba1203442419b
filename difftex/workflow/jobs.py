"""The workflow's jobs: which polygons share a texture job, and each job's memory and time limits.

A texture job starts a Python that imports torch and reads the scene (about 2 s of CPU on a
workstation, tens of seconds of queueing on a cluster); a small polygon's own work (a few
photos, a few thousand texels) is less than that. Small polygons therefore share a job, packed
largest first; large ones keep a job of their own, so a cluster still runs them side by side.
A shared job holds no more estimated seconds (``polygon_seconds``) than the largest polygon's
(nor more than ``run.pack_seconds``), so sharing does not lengthen a run on enough cores; but at least the
total over ``run.pack_jobs``, so that many equal small polygons still share, in about that many
jobs for the cores to run side by side. Jobs are named by their polygons (one polygon: its id;
several: a digest of their ids), so a rerun with the same polygons and config finds its jobs
done. The longest jobs start first (``priority``).

No torch here: the Snakefile's process calls these for every job.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path

from difftex.geometry.frames import level_sides
from difftex.scene.camera import IMAGE_SUFFIXES


def _first_photo(scene: str | Path, row: dict, measure, fallback: int) -> int:
    """``measure`` (a header reader) of the row's first photo, or ``fallback`` (a 12-Mpixel 8-bit
    photo's figure) when it has none or its header cannot be read."""
    for name in row.get("photos", [])[:1]:
        try:
            return int(measure(Path(scene) / "images" / name))
        except Exception:  # noqa: BLE001 -- an estimate only; the stage reports a bad photo itself
            break
    return fallback


def _photo_pixels(scene: str | Path, row: dict) -> int:
    from difftex.scene.files import image_size

    return _first_photo(scene, row, lambda path: math.prod(image_size(path)), 4000 * 3000)


def _photo_stored_bytes(scene: str | Path, row: dict) -> int:
    """Bytes of one of the row's photos as a shared job's decode cache keeps it (8/16-bit RGB, at
    full size: a job may decode at full size)."""
    from difftex.scene.files import image_stored_bytes

    return _first_photo(scene, row, image_stored_bytes, 4000 * 3000 * 3)


def polygon_mem_mb(scene: str | Path, row: dict, run: dict, top_k: int | None = None) -> int:
    """Memory of one polygon's optimization: texels x slots x bytes per slot (parameters, Adam
    state, mapped colours, masks, autograd temporaries), plus the candidate photos as float32 RGB,
    plus Python/torch. The optimizer keeps min(candidates, top_k) slots per texel, not one per
    candidate; every candidate photo is held (cropped) to map it at each level."""
    texels = int(row.get("width", 0)) * int(row.get("height", 0))
    k = len(row.get("photos", []))
    slots = min(k, int(top_k)) if top_k else k
    data = texels * slots * float(run["bytes_per_texel_photo"]) + k * _photo_pixels(scene, row) * 12
    return int(run["base_mem_mb"] + math.ceil(data / 2**20))


# Time of the render loss per texel x slot x iteration in units of the texel loss's, for the
# estimates: an iteration touches every photo pixel of the texels (2.7x the texel loss's time at
# 2048 texels on herzjesu's facade, evaluation/bench_optimize.md), and it has no sub-level of the
# unsettled texels (which the texel loss iterates on: 10-25 % of them at `balanced`).
RENDER_LOSS_COST = 20.0


def polygon_work(row: dict, cfg: dict) -> float:
    """Texel x slot x iteration count of a polygon's optimization at its iteration caps: every
    coarse-to-fine level (as the optimizer plans them) at min(candidates, top_k) slots; with the
    render loss, RENDER_LOSS_COST times that (``run.texels_per_minute`` is the texel loss's rate)."""
    opt = cfg["optimize"]
    w, h = int(row.get("width", 0)), int(row.get("height", 0))
    long_side = max(w, h, 1)
    k = max(1, min(len(row.get("photos", [])), int(opt.get("top_k", 8))))
    sides = level_sides(long_side, int(opt["long_side_start"]), bool(opt.get("coarse_to_fine", True)),
                        float(opt.get("level_step", 2.0)))
    caps = opt["max_iters_per_level"]
    caps = [int(c) for c in (caps if isinstance(caps, list) else [caps])]
    work = sum(w * h * (s / long_side) ** 2 * k * caps[min(i, len(caps) - 1)] for i, s in enumerate(sides))
    return work * (RENDER_LOSS_COST if opt.get("loss_mode") == "render" else 1.0)


def polygon_seconds(row: dict, cfg: dict) -> float:
    """Estimated seconds of a polygon's texturing: its optimization (``polygon_work`` at
    ``run.texels_per_minute``), mapping every candidate photo over its texels at each level
    (texels x candidates at ``run.texel_photos_per_second``: decoding, f_k^i, sampling,
    brightness transfers and ranking, which at `fast` cost more than the iterations) and a fixed
    set-up (``run.polygon_setup_s``). Fitted on the texture logs of herzjesu-p8 and the archive
    (200 and 50 photos) at `fast` and `balanced` (56 polygons, 0.1-48 s): correlation with the
    measured seconds 0.99, where the optimization term alone had 0.91 and put herzjesu's
    facade at half of `balanced`'s work instead of a third."""
    run = cfg["run"]
    texels = int(row.get("width", 0)) * int(row.get("height", 0))
    mapping = texels * len(row.get("photos", [])) / float(run["texel_photos_per_second"])
    return 60.0 * polygon_work(row, cfg) / float(run["texels_per_minute"]) + mapping + float(run["polygon_setup_s"])


def job_seconds(rows: list[dict], cfg: dict) -> float:
    """Estimated seconds of a job of these polygons (``polygon_seconds``)."""
    return sum(polygon_seconds(r, cfg) for r in rows)


def runtime_min(rows: list[dict], cfg: dict) -> int:
    """Wall-clock minutes for a cluster's time limit of a job of these polygons: their estimated
    seconds (``job_seconds``), 3x margin, at least 10."""
    return int(max(10, math.ceil(3 * job_seconds(rows, cfg) / 60.0)))


def priority(rows: list[dict], cfg: dict) -> int:
    """The scheduler's priority of a job of these polygons: its estimated seconds. Snakemake
    starts the ready jobs of highest priority first, so the longest jobs start first and the
    short ones fill the other cores around them (longest processing time first); in the order
    of the DAG, the largest polygon could start last and run alone on one core while the others
    idle."""
    return int(math.ceil(job_seconds(rows, cfg)))


def job_mem_mb(scene: str | Path, rows: list[dict], cfg: dict) -> int:
    """A job holds one polygon's data at a time (the largest of its polygons' estimates) and,
    with several polygons, up to ``run.decode_cache_mb`` of decoded photos (difftex.scene.files.
    DecodeCache, which keeps them as stored: 3 bytes a pixel for 8-bit photos, not float32's 12)."""
    mem = max(polygon_mem_mb(scene, r, cfg["run"], cfg["optimize"]["top_k"]) for r in rows)
    if len(rows) > 1:
        photos = {name for r in rows for name in r.get("photos", [])}
        cache = len(photos) * _photo_stored_bytes(scene, rows[0]) / 2**20
        mem += min(float(cfg["run"]["decode_cache_mb"]), cache)
    return int(math.ceil(mem))


def job_name(pids: list[str]) -> str:
    """One polygon: its id (its log is logs/texture/<id>.log); several: ``group-`` and a digest of
    their ids, so that another grouping is another job, never a stale one."""
    if len(pids) == 1:
        return pids[0]
    return "group-" + hashlib.sha1("\n".join(sorted(pids)).encode()).hexdigest()[:10]


# pack_jobs when the run's cores are not known to the process that plans the jobs (a cluster run:
# the main process and each job's own Snakemake must plan the same jobs)
PACK_JOBS_FALLBACK = 4


def pack_jobs(setting: int | str, local: bool, cores: int | None) -> int:
    """``run.pack_jobs`` as a number: ``auto`` is the cores of a local run, since the small
    polygons' shared jobs then run side by side on them; on a cluster (or when the cores are not
    known) PACK_JOBS_FALLBACK, the same in the main process and in every job's own Snakemake,
    whose core counts differ (a job's polygons must not depend on which process asks).

    Args:
        setting: the config value, an integer >= 1 or ``auto``.
        local: whether the jobs run on this machine (no executor plugin, not inside a cluster job).
        cores: the run's ``--cores``, or None.
    """
    if setting != "auto":
        return int(setting)
    if local and cores:
        return max(1, int(cores))
    return PACK_JOBS_FALLBACK


def cli_executor(argv: list[str]) -> str | None:
    """The executor a Snakemake command line (with its profiles) asks for, or None: local.

    While the Snakefile is read, Snakemake has not attached its executor plugin yet
    (``workflow.local_exec`` is True in a SLURM run's main process too), so the choice is read
    from the command line the way Snakemake reads it. A run started another way (the API) is
    taken as local.
    """
    import contextlib
    import io

    try:
        from snakemake.cli import parse_args

        # (quiet: Snakemake prints which profile it uses once itself)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            _, args = parse_args(list(argv))
    except (SystemExit, Exception):  # noqa: BLE001 -- not a snakemake command line
        return None
    executor = getattr(args, "executor", None)
    return None if executor in (None, "local", "dryrun", "touch") else str(executor)


def split_stages(setting: bool | str, gpu: int, local: bool) -> bool:
    """``run.split`` as a boolean: whether a polygon's work runs as three jobs (initialize,
    optimize, compose) or one (``texture``).

    ``auto`` splits where the split buys something: a job that requests a GPU (only the
    optimization then holds it) or a cluster run (the initializations run on CPU nodes while other
    polygons optimize). A local CPU run keeps one job, which saves the second process start and
    the crops' file (docs/stage-split.md measures both). The same answer in the main process and
    in every cluster job's own Snakemake, as ``pack_jobs``.

    Args:
        setting: the config value, true, false or ``auto``.
        gpu: ``run.gpu``.
        local: whether the jobs run on this machine (no executor plugin, not inside a cluster job).
    """
    if setting == "auto":
        return gpu > 0 or not local
    return bool(setting)


def texture_jobs(rows: list[dict], cfg: dict) -> dict[str, list[str]]:
    """Polygon ids per texture job, in a stable order.

    ``limit`` of estimated seconds (``polygon_seconds``) is ``run.pack_seconds``, or the largest
    polygon's if that is less (but not under the total over ``run.pack_jobs``). Polygons at the
    limit or above get a job each; the others share ceil(their seconds / limit) jobs, each
    polygon (largest first) joining, among the jobs it fits in, the one that already has most of
    its photos (the job decodes a photo once for all its polygons, difftex.scene.files.DecodeCache),
    else the least-loaded job; so a shared job ends within one small polygon (and
    ``run.photo_decode_s`` per photo it shares) of the limit.
    ``pack_seconds: 0`` gives every polygon its own job.

    Args:
        rows: the visibility summary's rows of the polygons to texture.
        cfg: the resolved config (``optimize`` and ``run`` sections).

    Returns:
        {job name: [polygon ids]}, jobs in order of their first polygon in ``rows``.
    """
    pack = float(cfg["run"].get("pack_seconds", 0))
    order = {str(r["id"]): i for i, r in enumerate(rows)}
    works = sorted(((polygon_seconds(r, cfg), str(r["id"])) for r in rows), key=lambda t: (-t[0], order[t[1]]))
    # A shared job no larger than the largest polygon's (run side by side, the shared jobs then
    # do not lengthen the run), but at least the total over pack_jobs (many equal small
    # polygons still share, in about pack_jobs jobs; not a fraction of pack_seconds, which
    # would put a small scene's polygons in one job on one core).
    total = sum(w for w, _ in works)
    n_jobs = pack_jobs(cfg["run"].get("pack_jobs", 1), local=False, cores=None)
    limit = min(pack, max(works[0][0] if works else 0.0, total / n_jobs))
    alone = [[pid] for work, pid in works if work >= limit]  # a job each
    small = [(work, pid) for work, pid in works if work < limit]
    # the small ones in as many jobs as their work needs at the limit, largest first, each added
    # to the job that already has most of its photos among those it fits in, else to the
    # least-loaded one: balanced jobs, each within one polygon (and the decodes it saves) of the limit
    n = max(1, math.ceil(sum(w for w, _ in small) / limit - 1e-9)) if small else 0
    photos = {str(r["id"]): set(r.get("photos") or ()) for r in rows}
    decode_s = float(cfg["run"].get("photo_decode_s", 0.0))
    shared: list[list] = [[0.0, [], set()] for _ in range(n)]
    for work, pid in small:
        mine = photos[pid]
        least = min(shared, key=lambda g: g[0])

        def fits(g, work=work, mine=mine, least=least) -> bool:
            # within the limit, allowing the decodes its shared photos save; the least-loaded job
            # always takes it (a job ends within one polygon of the limit, as without the photos)
            return g is least or g[0] + work <= limit + decode_s * len(mine & g[2])

        # the job that already decodes most of its photos (DecodeCache: a roof and the wall below
        # it share half their photos), then the least loaded
        best = max((g for g in shared if fits(g)), key=lambda g: (len(mine & g[2]), -g[0]))
        best[0] += work
        best[1].append(pid)
        best[2] |= mine
    groups = alone + [members for _, members, _ in shared if members]
    jobs = [sorted(members, key=order.__getitem__) for members in groups]
    jobs.sort(key=lambda m: order[m[0]])
    return {job_name(m): m for m in jobs}


def scene_mem_mb(scene_inputs_list: list[str], run: dict, factor: float = 4.0) -> int:
    """Whole-scene stages hold about one full-resolution photo and its id buffer at a time."""
    from difftex.scene.files import image_size

    pixels = 4000 * 3000
    for p in scene_inputs_list:
        if Path(p).suffix.lower() in IMAGE_SUFFIXES and "images" in Path(p).parts:
            try:
                w, h = image_size(p)
                pixels = w * h
            except Exception:  # noqa: BLE001 -- an estimate only
                pass
            break
    return int(run["base_mem_mb"] + math.ceil(pixels * 3 * 4 * factor / 2**20))


def assemble_mem_mb(polygon_rows: list[dict], cfg: dict) -> int:
    """Two float32 pages of the atlas at most plus the textures (as float32) of all polygons."""
    texels = sum(int(p.get("width", 0)) * int(p.get("height", 0)) for p in polygon_rows)
    page = int(cfg["assemble"]["max_page_size"]) ** 2
    page = min(page, int(texels * 1.3) + 1)
    return int(cfg["run"]["base_mem_mb"] + math.ceil((3 * page * 12 + texels * 13) / 2**20))


def filter_parts(scene_inputs_list: list[str], scene: str | Path, per_job: int) -> dict[str, list[str]]:
    """The filter stage's chunks: {part name: its photo files}, cut as the jobs cut them
    (difftex.scene.partition). A scene not yet on disk (the example before it is generated) has
    one part and no photo inputs; its job finds its photos when it runs.

    Args:
        scene_inputs_list: the scene's input files (proxy, model, photos), as the workflow lists them.
        scene: the scene folder.
        per_job: ``run.filter_photos_per_job``.
    """
    from difftex.scene.partition import part_name, parts_for, photo_chunk

    images = Path(scene) / "images"
    photos = [p for p in scene_inputs_list if Path(p).suffix.lower() in IMAGE_SUFFIXES]
    names = [Path(p).relative_to(images).as_posix() for p in photos]
    n = parts_for(len(names), per_job)
    return {part_name(j, n): [str(images / name) for name in photo_chunk(names, j, n)] for j in range(n)}


def visibility_tiles(scene: str | Path, per_job: int) -> list[str]:
    """The visibility stage's spatial tiles (names): ceil(polygons / per_job). The proxy is read
    for its polygon count; a proxy that is not there yet (the example) or cannot be read gives one
    tile, whose job reports the problem in one line as it would without tiles."""
    from difftex.errors import DifftexError
    from difftex.scene.loading import find_proxy
    from difftex.scene.partition import part_name, parts_for
    from difftex.scene.proxy import load_proxy

    quiet = logging.getLogger("difftex.scene.proxy")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # its warnings (skipped polygons) are the filter stage's to give, once
    try:
        count = len(load_proxy(find_proxy(Path(scene))).polygons)
    except (DifftexError, OSError):
        count = 0
    finally:
        quiet.setLevel(level)
    n = parts_for(count, per_job)
    return [part_name(j, n) for j in range(n)]


def gather_mem_mb(items: int, run: dict, mb_per_item: float = 0.05) -> int:
    """A merge of the scene stages' parts holds their records: ``mb_per_item`` per photo or
    polygon (a photo's record lists the polygons it sees with their angles) on top of Python's."""
    return int(run["base_mem_mb"] + math.ceil(items * mb_per_item))
