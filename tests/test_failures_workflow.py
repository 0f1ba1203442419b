"""The workflow's console and its runs' lives: what `snakemake` prints when a run fails (the
failed job's one `difftex: error:` line, last, exit status non-zero, no traceback), config
errors, read-only results, dry runs that change nothing, two runs in one folder, and runs
killed (SIGINT, SIGKILL) or starved of disk that the README's command resumes to the same
textures as an uninterrupted run.

Cheap cases stop at the first stage that must fail (a target early in the graph); the kill and
full-disk cases run the whole workflow on a 3-polygon copy of the small synthetic scene.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from difftex.layout import Results

from tests import breakage as B

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = REPO / "Snakefile"
BIN = Path(sys.executable).parent
# Small and quick: the kill test checks resuming, not the texture quality.
QUICK = (
    "preset=fast",
    "texture={long_side: 64}",
    "optimize={long_side_start: 32, max_iters_per_level: [5, 3]}",
    "run={evaluate: false}",
)
# the resume tests: a texture job, and so a finish job, per polygon, so that the gate (FinishGate)
# can hold the run between two polygons' textures
RESUME = (*QUICK[:-1], "run={evaluate: false, pack_seconds: 0}")


def snakemake_cmd(workdir: Path, *args: str) -> list[str]:
    return [str(BIN / "snakemake"), "-s", str(SNAKEFILE), "--directory", str(workdir), "--cores", "2", *args]


def env(**extra: str) -> dict:
    return dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", OMP_NUM_THREADS="1", **extra)


def snakemake(workdir: Path, *args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    """Run snakemake; stdout and stderr merged in order, as a terminal shows them."""
    return subprocess.run(snakemake_cmd(workdir, *args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, timeout=timeout, env=env())


def console_lines(r) -> list[str]:
    return [ln for ln in r.stdout.splitlines() if ln.strip()]


def assert_console_error(r, *needles) -> str:
    """Non-zero exit, the last console line is the one `difftex: error:` line with the needles,
    and no Python traceback anywhere."""
    lines = console_lines(r)
    assert r.returncode != 0, r.stdout[-3000:]
    assert lines and lines[-1].startswith("difftex: error: "), r.stdout[-3000:]
    assert "Traceback" not in r.stdout, r.stdout[-3000:]
    for n in needles:
        assert n in lines[-1], (n, lines[-1])
    return lines[-1]


@pytest.fixture
def scene(small_synth_scene, tmp_path) -> Path:
    return B.copy_scene(small_synth_scene, tmp_path / "small")


def photos_target(name: str = "small") -> str:
    return str(Results(f"results/{name}").photos_json)


# ---------------------------------------------------------------------------------------------
# The console of a failed run


def test_failed_job_ends_the_console_with_its_error_line(scene, tmp_path):
    B.set_camera(scene, 0, lambda t: [*t[:4], "0", *t[5:]])
    work = tmp_path / "work"
    r = snakemake(work, photos_target(), "--config", f"scene={scene}")
    line = assert_console_error(r, "cameras.txt", "camera 1", "focal length 0")
    assert "img_" not in line  # the camera's fault, not a photo's
    lines = console_lines(r)
    failed = "difftex: 1 job failed; log: results/small/logs/filter/001-of-001.log"
    assert any(ln.startswith(failed) for ln in lines[-3:])
    assert not (work / photos_target()).exists() and B.temp_files(work / "results") == []


def test_every_photo_filtered_out_stops_at_the_filter(scene, tmp_path):
    for k in range(B.n_images(scene)):
        B.turn_camera_around(scene, k)
    r = snakemake(tmp_path / "w", photos_target(), "--config", f"scene={scene}")
    assert_console_error(r, "images", "every photo was filtered out")


def test_warnings_reach_the_console_once(scene, tmp_path):
    from scipy.ndimage import gaussian_filter

    from difftex.scene.files import read_image, write_image

    shutil.copy(scene / "images" / "img_0000.png", scene / "images" / "extra.png")
    blurred = scene / "images" / "img_0003.png"  # dropped as blurry: said on the console, not only in photos.csv
    write_image(blurred, gaussian_filter(read_image(blurred), sigma=(3, 3, 0)))
    r = snakemake(tmp_path / "w", photos_target(), "--config", f"scene={scene}")
    assert r.returncode == 0, r.stdout[-3000:]
    warned = [ln for ln in console_lines(r) if ln.startswith("difftex: warning: ")]
    hits = [ln for ln in warned if "not in the COLMAP model" in ln]
    assert len(hits) == 1 and "extra.png" in hits[0], r.stdout[-3000:]
    hits = [ln for ln in warned if "dropped as blurry" in ln]
    assert len(hits) == 1 and "1 photo dropped as blurry" in hits[0] and "img_0003.png (" in hits[0], warned


@pytest.mark.parametrize(
    "config, needles",
    [
        (("optimize={lrr: 1}",), ["invalid configuration", "lrr"]),
        (("preset=fastest",), ["unknown preset 'fastest'"]),
        (("scene=/nowhere/at/all",), ["/nowhere/at/all", "scene folder not found"]),
        (("texture={long_side: 0}",), ["texture.long_side"]),
    ],
    ids=["unknown-key", "unknown-preset", "no-scene-folder", "bad-value"],
)
def test_config_errors_are_one_line(config, needles, scene, tmp_path):
    args = ("--config", f"scene={scene}", *config) if not config[0].startswith("scene=") else ("--config", *config)
    r = snakemake(tmp_path / "w", *args)
    assert_console_error(r, *needles)
    # nothing but Snakemake's note on the profile before it: no Snakemake frame around it
    assert len(console_lines(r)) <= 2 and "WorkflowError" not in r.stdout, r.stdout


def test_read_only_results_folder(scene, tmp_path):
    work = tmp_path / "w"
    undo = B.make_unwritable(work / "results")
    if undo is None:
        pytest.skip("cannot make a folder read-only here (root without chattr)")
    try:
        r = snakemake(work, photos_target(), "--config", f"scene={scene}")
    finally:
        undo()
    assert_console_error(r, "results", "not writable")


def test_scene_path_with_spaces_and_accents(small_synth_scene, tmp_path):
    scene = B.copy_scene(small_synth_scene, tmp_path / "Kölner Dom (west)")
    work = tmp_path / "work dir"
    target = Results("results/Kölner_Dom_west").visibility_summary
    r = snakemake(work, str(target), "--config", f"scene={scene}", *QUICK)
    assert r.returncode == 0, r.stdout[-3000:]
    summary = json.loads((work / target).read_text())
    assert len(summary["polygons"]) == 6


def test_dry_run_changes_nothing(scene, tmp_path):
    work = tmp_path / "w"
    r = snakemake(work, "-n", "--config", f"scene={scene}", "preset=fast")
    assert r.returncode == 0, r.stdout[-3000:]
    assert sorted(p.name for p in work.iterdir()) == [".snakemake"]
    # after a (partial) real run, a dry run with changed settings rewrites nothing either
    assert snakemake(work, photos_target(), "--config", f"scene={scene}", "preset=fast").returncode == 0
    before = {p: p.stat().st_mtime_ns for p in (work / "results").rglob("*")}
    r = snakemake(work, "-n", "--config", f"scene={scene}", "preset=fast", "filter={blur_ratio: 0.2}")
    assert r.returncode == 0 and "filter" in r.stdout
    assert {p: p.stat().st_mtime_ns for p in (work / "results").rglob("*")} == before


# ---------------------------------------------------------------------------------------------
# Whole runs: interrupted, killed, two at once, a full disk


def three_polygon_scene(small_synth_scene: Path, dst: Path) -> Path:
    """The small scene with three of its polygons, so that a whole run takes tens of seconds."""
    from difftex.scene.proxy import load_proxy, write_proxy_obj

    scene = B.copy_scene(small_synth_scene, dst)
    proxy = load_proxy(scene / "proxy.obj")
    write_proxy_obj(scene / "proxy.obj", [p for p in proxy.polygons if p.id in ("wall00", "wall02", "roof00")])
    return scene


@pytest.fixture(scope="module")
def resume_scene(small_synth_scene, tmp_path_factory) -> Path:
    return three_polygon_scene(small_synth_scene, tmp_path_factory.mktemp("resume") / "small")


@pytest.fixture(scope="module")
def reference_run(resume_scene, tmp_path_factory) -> Path:
    """An uninterrupted run of the README command on the 3-polygon scene."""
    work = tmp_path_factory.mktemp("reference")
    r = snakemake(work, "--config", f"scene={resume_scene}", *RESUME)
    assert r.returncode == 0, r.stdout[-3000:]
    return work / "results" / "small"


def textures(results: Path) -> dict[str, bytes]:
    return {str(p.relative_to(results)): p.read_bytes() for p in sorted(Results(results).textures_dir.rglob("*.png"))}


def wait_for(cond, proc, what: str, timeout: float = 600):
    t0 = time.time()
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"the run ended (status {proc.returncode}) before {what}")
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def n_textures(work: Path) -> int:
    return len(glob.glob(str(Results(work / "results/small").texture("*"))))


def start(work: Path, log: Path, *args: str, extra_env: dict | None = None) -> subprocess.Popen:
    # its own session: the signal goes to Snakemake and its jobs, as Ctrl-C or a power cut would
    # SIGINT back to its default: a shell's background job (e.g. CI under nohup ... &) starts with
    # it ignored, Python then keeps it ignored, and Ctrl-C would not reach Snakemake at all
    return subprocess.Popen(snakemake_cmd(work, *args), stdout=open(log, "w"), stderr=subprocess.STDOUT,
                            env=env(**(extra_env or {})), start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


class FinishGate:
    """Holds the workflow's ``difftex finish`` jobs (the step that writes a polygon's texture.png)
    while ``limit`` or more texture.png files exist; every other command runs unchanged. The test
    sets the limit and waits until a finish job is held with that many textures made (``held``):
    the run then stands in the per-polygon stage with its earlier jobs complete (one job at a
    time: the held one started after they ended), however fast or loaded the machine is. It can
    neither finish early nor be interrupted before its first texture.

    The jobs' shell (bash) finds ``difftex`` as a function exported in the run's environment
    (``BASH_FUNC_difftex%%``) before the PATH, which the workflow's shell prefix sets to the
    venv's bin folder: the function runs ``hold.py`` for ``finish`` and then the real command."""

    def __init__(self, folder: Path, textures: Path):
        self.folder = folder
        folder.mkdir(parents=True)
        self.limit(0)
        hold = folder / "hold.py"
        hold.write_text(
            "import os, sys, time\n"
            f"gate, textures = {str(folder)!r}, {str(textures)!r}\n"
            "def made():\n"
            "    return sum(os.path.isfile(os.path.join(textures, d, 'texture.png'))\n"
            "               for d in (os.listdir(textures) if os.path.isdir(textures) else []))\n"
            "t0 = time.monotonic()\n"
            "while (n := made()) >= int(open(os.path.join(gate, 'limit')).read()):\n"
            "    open(os.path.join(gate, f'held-at-{n}'), 'w').close()\n"
            "    if time.monotonic() - t0 > 900:  # a test that died and left its run behind\n"
            "        sys.exit('difftex (test gate): held for 900 s')\n"
            "    time.sleep(0.02)\n"
        )
        self.env = {
            "BASH_FUNC_difftex%%": (
                f'() {{ if [ "${{1-}}" = finish ]; then "{sys.executable}" "{hold}" || return 1; fi; '
                'command difftex "$@"; }'
            )
        }

    def limit(self, n: int) -> None:
        tmp = self.folder / "limit.tmp"
        tmp.write_text(str(n))
        tmp.replace(self.folder / "limit")

    def held(self, n: int) -> bool:
        """Whether a finish job is (or was) held with ``n`` textures made."""
        return (self.folder / f"held-at-{n}").exists()


def test_interrupted_and_killed_runs_resume_to_the_same_textures(resume_scene, reference_run, tmp_path):
    work = tmp_path / "w"
    # one job at a time (the last --cores wins), so that the gate's count of textures is exact
    args = ("--config", f"scene={resume_scene}", *RESUME, "--cores", "1")
    total = len(textures(reference_run)) // 3  # texture, source, coverage per polygon
    assert total == 3
    gate = FinishGate(tmp_path / "gate", work / "results/small/textures")
    runs: list[subprocess.Popen] = []
    try:
        _interrupt_kill_and_resume(work, args, total, gate, runs, reference_run, tmp_path)
    finally:
        for p in runs:  # a failed assertion must not leave a held run behind
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def _interrupt_kill_and_resume(work, args, total, gate, runs, reference_run, tmp_path):
    # 1. a run (held before its first texture), and a second one started in the same folder
    # meanwhile: refused, one line
    first = start(work, tmp_path / "first.log", *args, extra_env=gate.env)
    runs.append(first)
    lock = work / ".snakemake/difftex/run.lock"

    def holds_lock():
        try:
            return json.loads(lock.read_text().splitlines()[0])["pid"] == first.pid
        except (OSError, ValueError, IndexError, KeyError):
            return False

    wait_for(holds_lock, first, "the first run took the run lock")
    second = snakemake(work, *args)
    assert_console_error(second, str(work), f"pid {first.pid}", "is using this folder")

    # 2. Ctrl-C (SIGINT) during the per-polygon stage: one texture made, the next one held
    gate.limit(1)
    wait_for(lambda: gate.held(1), first, "the first texture, and the next finish job held")
    os.killpg(first.pid, signal.SIGINT)
    status = first.wait(timeout=120)
    said = [ln for ln in (tmp_path / "first.log").read_text().splitlines() if ln.strip()]
    assert status == 130, said[-40:]
    assert said[-1] == "difftex: interrupted; run the same command again to resume", said[-5:]
    done = n_textures(work)
    assert done == 1

    # 3. the same command resumes; SIGKILL (a power cut) once it has made one more texture
    again = start(work, tmp_path / "again.log", *args, extra_env=gate.env)
    runs.append(again)
    gate.limit(done + 1)
    wait_for(lambda: gate.held(done + 1), again, "a texture after the resume, and the next finish job held")
    os.killpg(again.pid, signal.SIGKILL)
    again.wait(timeout=60)
    assert n_textures(work) == done + 1 < total
    assert (work / ".snakemake/locks").is_dir() and any((work / ".snakemake/locks").iterdir())  # stale locks

    # 4. the README command, unchanged: resumes by itself, same textures as without interruptions
    last = snakemake(work, *args)
    assert last.returncode == 0, last.stdout[-3000:]
    assert "difftex: resuming after a run that did not end cleanly" in last.stdout
    assert textures(work / "results/small") == textures(reference_run)
    assert B.temp_files(work / "results") == []


def test_full_disk_fails_in_one_line_and_the_rerun_completes(resume_scene, reference_run, tmp_path):
    """Results on a small filesystem that fills up during the run; after freeing space the same
    command completes with the reference's textures. Needs root for the tmpfs mount."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        ballast = disk / "ballast"
        free = 160 * 1024  # the filter and visibility fit, not the per-polygon outputs
        ballast.write_bytes(b"\0" * (shutil.disk_usage(disk).free - free))
        work = tmp_path / "w"
        args = ("--config", f"scene={resume_scene}", f"results={disk}/results", *RESUME)
        r = snakemake(work, *args)
        line = assert_console_error(r)
        assert "No space left on device" in line or "empty log" in line, line
        assert B.temp_files(disk) == []
        ballast.unlink()  # free the space
        r = snakemake(work, *args)
        assert r.returncode == 0, r.stdout[-3000:]
        assert textures(disk / "results/small") == textures(reference_run)
    finally:
        subprocess.run(["umount", str(disk)], check=False)
