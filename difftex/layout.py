"""The layout of a results folder: every file name the stages write, in one place.

A run of the workflow on scene ``<scene>`` writes the results folder ``R = <results>/<scene
name>/`` (``difftex.workflow.glue.scene_name``); the baselines and peers write folders of the
same layout, so ``difftex evaluate`` and ``difftex report`` read them all alike::

    R/
      photos.json, photos.csv          filter: the kept photos per polygon, and why each was dropped
      filter/photos-<part>.json        filter: one chunk of photos (merged into photos.json)
      dense/                           dense stereo (GPU, dense.stereo): a COLMAP dense workspace,
                                       stereo/depth_maps/*.geometric.bin, and dense.json
      visibility/
        <pid>.npz                      a polygon's UV frame, texel mask and candidate photos
        summary.json                   every polygon's row: the checkpoint the polygon jobs come from
        tiles/<tile>.json              one spatial tile's rows (merged into summary.json)
      visibility.txt                   instead of visibility/: the folder of a shared one (evaluation)
      init/                            initialization (run.split)
        <pid>/crops.npz                the candidate photos decoded and cropped to the polygon
        jobs/<job>.json                a job's list of its polygons, written last
      histmatch/                       histogram matching (run.split)
        <pid>/transfers.npz            the brightness transfers (and the relief the photos are
                                       mapped through), an input of the optimization
        jobs/<job>.json                a job's list of its polygons
      optimized/
        <pid>/weights.npz              slots, weights (float16) and brightness transfers
        <pid>/optimized.npz            composition's inputs (run.split)
        <pid>/stats.json               the optimizer's statistics (levels, losses, device)
        <pid>/composite.npz            the composed float texture, its source map and report
        jobs/<job>.json                a texture job's list (one process for the three stages)
        jobs/<job>.optimize.json       an optimize job's list (run.split)
        jobs/<job>.compose.json        a compose job's list (run.split)
      textures/
        <pid>/texture.png              the texture; with source.png (source map), source.npz (its
                                       photo indices), coverage.png, report.json, and maybe
                                       texture.exr, height.exr, normal.png
        jobs/<job>.json                a finish job's list
      model/                           assembly: model.obj/.mtl/.glb, atlas pages, summary.json,
                                       model_view.png, tileset/tileset.json with tileset/tiles/
      evaluation/metrics.json          the metrics, with error_maps/<pid>.png (against the ground
                                       truth) and views/<photo>_{render,photo,error}.png beside it
      config/<stage>-<digest>.yaml     a stage's config sections, named by their content
      config/compute.yaml              device and compilation (changes no result)
      logs/<rule>.log, logs/<rule>/<name>.log
      benchmarks/<rule>/<name>.tsv     Snakemake's benchmark of a job
      report.md, report/index.html     the run's summary, and the HTML report
      peer.json                        a peer's run (difftex peer)

A polygon's folders are named by its id (``<pid>``), a job's files by its name (``<job>``:
the polygon's id or ``group-<digest>``). Every method takes these as strings, so the workflow
passes Snakemake's wildcards (``"{job}"``) and gets the rule's pattern back unexpanded.

Stages that get a polygon's folder on their command line (``--out-dir R/optimized/<pid>``) name
the files in it with the constants below, so they write what :class:`Results` says is there.
This module imports the standard library only (the core layer): every layer may use it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# The files in a polygon's folder of optimized/ (the texturing stages)
WEIGHTS = "weights.npz"
OPTIMIZED = "optimized.npz"
STATS = "stats.json"
COMPOSITE = "composite.npz"
# ... of init/ and histmatch/
CROPS = "crops.npz"
TRANSFERS = "transfers.npz"
# ... and of textures/ (the finish stage, the baselines, the peers)
TEXTURE = "texture.png"
TEXTURE_EXR = "texture.exr"
SOURCE_PNG = "source.png"
SOURCE_NPZ = "source.npz"
COVERAGE = "coverage.png"
REPORT = "report.json"
HEIGHT = "height.exr"
NORMAL = "normal.png"

# The summary of the visibility folder and of the model folder
SUMMARY = "summary.json"
# The model's files are <MODEL_NAME>.obj, .mtl, .glb, <MODEL_NAME>_atlas<k>.png ...
MODEL_NAME = "model"
TILESET_DIR = "tileset"
TILESET = "tileset.json"
TILES_DIR = "tiles"  # beside tileset.json: one GLB per building
# What the evaluation writes beside its metrics
ERROR_MAPS = "error_maps"
VIEWS = "views"
# The dense stage's record in its COLMAP workspace (difftex.scene.mvs), written last
DENSE_RECORD = "dense.json"

# The folder, relative to R, and the suffix of each per-polygon rule's list of its polygons
# (written last, so it is the job's one output)
JOB_FILES = {
    "initialize": ("init", ".json"),
    "histmatch": ("histmatch", ".json"),
    "texture": ("optimized", ".json"),
    "optimize": ("optimized", ".optimize.json"),
    "compose": ("optimized", ".compose.json"),
    "finish": ("textures", ".json"),
}

# The files each per-polygon rule's job leaves in a polygon's folder (besides its job file), by the
# folder's name relative to R. A finished job missing one of them is run again (difftex.workflow.
# products); height.exr and normal.png are left out: finish writes them only with a relief.
POLYGON_PRODUCTS = {
    "initialize": ("init", (CROPS,)),
    "histmatch": ("histmatch", (TRANSFERS,)),
    "optimize": ("optimized", (WEIGHTS, OPTIMIZED, STATS)),
    "compose": ("optimized", (COMPOSITE,)),
    "texture": ("optimized", (WEIGHTS, STATS, COMPOSITE)),
    "finish": ("textures", (TEXTURE, SOURCE_PNG, SOURCE_NPZ, COVERAGE, REPORT)),
}


def polygon_products(res: Results, rule: str, pid: str, exr: bool = False) -> list[Path]:
    """The files a job of a per-polygon rule writes for polygon ``pid`` (POLYGON_PRODUCTS).

    Args:
        res: the results folder.
        rule: initialize, histmatch, optimize, compose, texture or finish.
        pid: the polygon's id.
        exr: finish also writes texture.exr (``output.exr``).
    """
    folder, names = POLYGON_PRODUCTS[rule]
    if rule == "finish" and exr:
        names = (*names, TEXTURE_EXR)
    return [res.root / folder / pid / name for name in names]


def visibility_file(folder: str | Path, pid: str) -> Path:
    """A polygon's visibility file in a visibility folder (R/visibility or one given to a command).

    Args:
        folder: the visibility folder.
        pid: the polygon's id.

    Returns:
        ``folder/<pid>.npz``.
    """
    return Path(folder) / f"{pid}.npz"


def error_map_file(folder: str | Path, pid: str) -> Path:
    """A polygon's error map against its ground-truth map, in an error map folder."""
    return Path(folder) / f"{pid}.png"


def view_file(folder: str | Path, photo: str, kind: str) -> Path:
    """An image of a held-out view in a views folder.

    Args:
        folder: the views folder.
        photo: the held-out photo's name (its stem names the files).
        kind: "render" (the textured model from the photo's camera), "photo" or "error".

    Returns:
        ``folder/<photo stem>_<kind>.png``.
    """
    return Path(folder) / f"{Path(photo).stem}_{kind}.png"


@dataclass(frozen=True)
class Results:
    """The paths of one results folder.

    Args:
        root: the folder R (a str is turned into a Path); every path is under it.
    """

    root: Path

    def __post_init__(self):
        # frozen: the dataclass's own way to convert a field after __init__
        object.__setattr__(self, "root", Path(self.root))

    # --- filter

    @property
    def photos_json(self) -> Path:
        return self.root / "photos.json"

    @property
    def photos_csv(self) -> Path:
        return self.root / "photos.csv"

    def filter_part(self, part: str) -> Path:
        """One chunk's table, ``part`` as ``<j>-of-<n>``."""
        return self.root / "filter" / f"photos-{part}.json"

    # --- dense stereo (GPU)

    @property
    def dense_dir(self) -> Path:
        """R/dense: the COLMAP dense workspace of ``difftex dense`` (images/, sparse/, stereo/depth_maps/)."""
        return self.root / "dense"

    @property
    def dense_done(self) -> Path:
        """R/dense/dense.json: the dense stage's record (done or skipped), in place once the workspace is."""
        return self.dense_dir / DENSE_RECORD

    # --- visibility

    @property
    def visibility_dir(self) -> Path:
        return self.root / "visibility"

    @property
    def visibility_link(self) -> Path:
        """R/visibility.txt: the visibility folder that this one shares, when it has none of its own."""
        return self.root / "visibility.txt"

    def visibility(self, pid: str) -> Path:
        return visibility_file(self.visibility_dir, pid)

    @property
    def visibility_summary(self) -> Path:
        return self.visibility_dir / SUMMARY

    def visibility_tile(self, tile: str) -> Path:
        """One spatial tile's rows, ``tile`` as ``<j>-of-<n>``."""
        return self.visibility_dir / "tiles" / f"{tile}.json"

    # --- relief from dense geometry

    @property
    def heights_dir(self) -> Path:
        """R/heights: one <pid>.npz height field per polygon (difftex.compose.heights)."""
        return self.root / "heights"

    def heights_tile(self, tile: str) -> Path:
        """The heights stage's list of one visibility tile's polygons."""
        return self.heights_dir / "tiles" / f"{tile}.json"

    # --- the per-polygon stages

    @property
    def init_dir(self) -> Path:
        return self.root / "init"

    def crops(self, pid: str) -> Path:
        return self.init_dir / pid / CROPS

    @property
    def histmatch_dir(self) -> Path:
        return self.root / "histmatch"

    def transfers(self, pid: str) -> Path:
        """R/histmatch/<pid>/transfers.npz: the histogram-matching stage's file (run.split)."""
        return self.histmatch_dir / pid / TRANSFERS

    @property
    def optimized_dir(self) -> Path:
        return self.root / "optimized"

    def polygon_optimized(self, pid: str) -> Path:
        """R/optimized/<pid>: the folder the texturing stages write a polygon's files to."""
        return self.optimized_dir / pid

    def weights(self, pid: str) -> Path:
        return self.polygon_optimized(pid) / WEIGHTS

    def optimized(self, pid: str) -> Path:
        return self.polygon_optimized(pid) / OPTIMIZED

    def stats(self, pid: str) -> Path:
        return self.polygon_optimized(pid) / STATS

    def composite(self, pid: str) -> Path:
        return self.polygon_optimized(pid) / COMPOSITE

    @property
    def textures_dir(self) -> Path:
        return self.root / "textures"

    def polygon_textures(self, pid: str) -> Path:
        """R/textures/<pid>: a polygon's texture.png and the files beside it."""
        return self.textures_dir / pid

    def texture(self, pid: str) -> Path:
        return self.polygon_textures(pid) / TEXTURE

    def job_file(self, rule: str, job: str) -> Path:
        """The list of its polygons that a job of a per-polygon rule writes last.

        Args:
            rule: initialize, histmatch, texture, optimize, compose or finish.
            job: the job's name, or a wildcard (``"{job}"``) for the rule's pattern.

        Returns:
            e.g. R/optimized/jobs/<job>.optimize.json.
        """
        folder, suffix = JOB_FILES[rule]
        return self.root / folder / "jobs" / f"{job}{suffix}"

    # --- assembly, evaluation, reports

    @property
    def model_dir(self) -> Path:
        return self.root / "model"

    @property
    def model_summary(self) -> Path:
        return self.model_dir / SUMMARY

    def model_file(self, suffix: str) -> Path:
        """The model's file of this suffix (".obj", ".glb", "_view.png" ...)."""
        return self.model_dir / f"{MODEL_NAME}{suffix}"

    @property
    def tileset(self) -> Path:
        return self.model_dir / TILESET_DIR / TILESET

    @property
    def evaluation_dir(self) -> Path:
        return self.root / "evaluation"

    @property
    def metrics(self) -> Path:
        return self.evaluation_dir / "metrics.json"

    def error_map(self, pid: str) -> Path:
        return error_map_file(self.evaluation_dir / ERROR_MAPS, pid)

    @property
    def views_dir(self) -> Path:
        return self.evaluation_dir / VIEWS

    def view(self, photo: str, kind: str) -> Path:
        """A held-out view's image (``view_file``)."""
        return view_file(self.views_dir, photo, kind)

    @property
    def report_md(self) -> Path:
        return self.root / "report.md"

    @property
    def report_html(self) -> Path:
        return self.root / "report" / "index.html"

    @property
    def peer_record(self) -> Path:
        """R/peer.json: a peer's settings, photos and timings (difftex peer)."""
        return self.root / "peer.json"

    # --- the workflow's own files

    def stage_config(self, stage: str, digest: str) -> Path:
        """A stage's config file, named by its content (``digest``: 12 hex digits of its SHA-256)."""
        return self.root / "config" / f"{stage}-{digest}.yaml"

    @property
    def compute_config(self) -> Path:
        """The compute section, under a fixed name: a change of it reruns nothing."""
        return self.root / "config" / "compute.yaml"

    @property
    def logs_dir(self) -> Path:
        return self.root / "logs"

    def log(self, rule: str, name: str | None = None) -> Path:
        """R/logs/<rule>.log of a rule with one job, R/logs/<rule>/<name>.log of one of many (the
        filter's and visibility's parts log beside their merge, under filter/ and visibility/)."""
        if name is None:
            return self.logs_dir / f"{rule}.log"
        return self.logs_dir / rule / f"{name}.log"

    @property
    def benchmarks_dir(self) -> Path:
        return self.root / "benchmarks"

    def benchmark(self, rule: str, name: str) -> Path:
        """R/benchmarks/<rule>/<name>.tsv; the report sums a rule's jobs by this folder."""
        return self.benchmarks_dir / rule / f"{name}.tsv"
