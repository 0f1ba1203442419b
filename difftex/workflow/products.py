"""The per-polygon files of finished jobs: a job that lost one runs again.

Snakemake knows a per-polygon job by its one output, the list of its polygons that it writes last
(``R/<stage>/jobs/<job>...json``, difftex.layout.JOB_FILES), and a visibility tile's job by its
rows (``R/visibility/tiles/<tile>.json``). The polygons' own files (texture.png, composite.npz,
crops.npz ...; difftex.layout.POLYGON_PRODUCTS; and each polygon's visibility file) cannot be
outputs of such a job: a rule's outputs are patterns of its wildcards, and small polygons share a
job whose polygons come from the visibility checkpoint. A job per polygon would declare them, at the price of a process
start per polygon, thousands on a district. So Snakemake does not see a deleted texture.png: the
same command would say "Nothing to be done" and the evaluation would run without the texture.

Instead, when Snakemake starts to build its job graph (an input function of the ``all`` rule,
after the run lock is taken: difftex.workflow.runguard), ``Rebuild`` looks for the finished jobs
(their list is there) one of whose polygons' files is missing and deletes their lists. (Snakemake
makes a missing intermediate file again only for a job that must run, so the ``all`` rule asks for
every job's list.) Snakemake
then sees those jobs' output missing and runs them again; they write the same files (each stage
is deterministic), and what follows reruns only where a job's list changed. Only a real run
deletes anything; a dry run says which files a run would make again, and changes nothing.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path

from difftex.errors import DifftexError
from difftex.layout import Results, polygon_products
from difftex.scene.files import read_json

# The per-polygon rules of each way to run them (difftex.workflow.jobs.split_stages)
SPLIT_RULES = ("initialize", "histmatch", "optimize", "compose", "finish")
ONE_JOB_RULES = ("texture", "finish")
MAX_LINES = 5  # jobs named one a line; the rest counted
PREFIX = "difftex: "  # as the run guard's line on resuming: news, not a warning


def missing_products(res: Results, jobs: dict[str, list[str]], rules: Iterable[str],
                     exr: bool = False) -> dict[Path, list[Path]]:
    """The finished jobs whose polygons' files are not all there.

    Args:
        res: the results folder.
        jobs: {job name: its polygon ids} (difftex.workflow.jobs.texture_jobs).
        rules: the per-polygon rules that run (SPLIT_RULES or ONE_JOB_RULES).
        exr: whether finish writes texture.exr too (``output.exr``).

    Returns:
        {a finished job's list: the missing files of its polygons}, in the order of ``rules``
        and ``jobs``; a job whose list is missing is not finished (Snakemake runs it anyway).
    """
    out: dict[Path, list[Path]] = {}
    for rule in rules:
        for job, pids in jobs.items():
            job_file = res.job_file(rule, job)
            if not job_file.is_file():
                continue
            gone = [f for pid in pids for f in polygon_products(res, rule, pid, exr) if not f.is_file()]
            if gone:
                out[job_file] = gone
    return out


def missing_visibility(res: Results, tiles: Iterable[str]) -> dict[Path, list[Path]]:
    """The finished visibility tiles (their rows are there) whose polygons' visibility files are
    not all there: {a tile's rows file: the missing files}."""
    out: dict[Path, list[Path]] = {}
    for tile in tiles:
        rows = res.visibility_tile(tile)
        if not rows.is_file():
            continue
        try:
            ids = [str(r["id"]) for r in read_json(rows)["rows"]]
        except (DifftexError, KeyError, TypeError):  # unreadable: the merge reports it in one line
            continue
        gone = [res.visibility(pid) for pid in ids if not res.visibility(pid).is_file()]
        if gone:
            out[rows] = gone
    return out


def report_lines(missing: dict[Path, list[Path]], real: bool) -> list[str]:
    """One line per job (at most MAX_LINES, then a count): its first missing file and the job."""
    what = "runs again" if real else "would run again (this is a dry run)"
    lines = []
    for job_file, files in list(missing.items())[:MAX_LINES]:
        more = f" and {len(files) - 1} more of its files" if len(files) > 1 else ""
        lines.append(f"{PREFIX}{files[0]}{more} missing: the job that wrote them ({job_file}) {what}")
    if len(missing) > MAX_LINES:
        lines.append(f"{PREFIX}... and {len(missing) - MAX_LINES} more jobs whose files are missing")
    return lines


class Rebuild:
    """Snakemake input-function hook (after the run lock): finished per-polygon jobs that lost a
    polygon's file run again. Acts once per Snakemake process; returns no inputs.

    Args:
        results: the results folder R.
        cfg: the resolved config (the jobs' packing reads ``optimize`` and ``run``; ``output.exr``).
        split: whether the per-polygon stages run split (SPLIT_RULES) or as one job.
        tiles: the visibility stage's tiles (difftex.workflow.jobs.visibility_tiles).
    """

    def __init__(self, results: str | Path, cfg: dict, split: bool, tiles: Iterable[str] = ()) -> None:
        self.res = Results(Path(results))
        self.cfg = cfg
        self.rules = SPLIT_RULES if split else ONE_JOB_RULES
        self.tiles = list(tiles)
        self.checked = False

    def __call__(self, workflow) -> list:
        from difftex.workflow.runguard import is_real_run

        if self.checked:
            return []
        self.checked = True
        real = is_real_run(workflow)
        if real or getattr(workflow, "dryrun", False):
            self.rebuild(real)
        return []

    def rebuild(self, real: bool) -> dict[Path, list[Path]]:
        """Delete (``real``) the lists of the finished jobs that lost a file, and say so on stderr;
        returns them (``missing_visibility`` and ``missing_products``)."""
        missing = missing_visibility(self.res, self.tiles)
        missing.update(self._missing_products())
        if real:
            for job_file in missing:
                job_file.unlink(missing_ok=True)
        for line in report_lines(missing, real):
            print(line, file=sys.stderr, flush=True)
        return missing

    def _missing_products(self) -> dict[Path, list[Path]]:
        """``missing_products`` of the jobs the visibility summary plans; none before it exists
        (no per-polygon job has run)."""
        from difftex.workflow.glue import texture_jobs

        summary = self.res.visibility_summary
        if not summary.is_file():
            return {}
        try:
            jobs = texture_jobs(summary, self.cfg)
        except DifftexError:  # a broken summary: the visibility stage reports it when it reruns
            return {}
        return missing_products(self.res, jobs, self.rules, bool(self.cfg["output"].get("exr")))
