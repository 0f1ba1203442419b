"""The run lock and the end-of-run report, without Snakemake runs (those are in
test_failures_workflow.py): refusal of a second run, what a dead run leaves and what is cleaned,
the lines the console gets from job logs, and Ctrl-C outside Snakemake's scheduler."""

from __future__ import annotations

import signal
import subprocess
import sys
from base64 import urlsafe_b64encode
from pathlib import Path

import pytest

from difftex.workflow import runguard, runlog


def test_second_guard_in_the_same_folder_is_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    first = runguard.RunGuard("results/s", workdir=tmp_path)
    first.acquire()
    second = runguard.RunGuard("results/s", workdir=tmp_path)
    with pytest.raises(SystemExit) as info:
        second.acquire()
    assert info.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difftex: error: ") and "is using this folder" in err[0]
    import os

    assert f"pid {os.getpid()}" in err[0]
    # the lock dies with its holder: a new guard gets it
    os.close(first.fd)
    runguard.RunGuard("results/s", workdir=tmp_path).acquire()


def _mark_incomplete(workdir: Path, key: str, max_len: int = 255) -> None:
    """A marker as Snakemake's file persistence writes it (urlsafe base64 of the output path, cut
    into '@'-prefixed folders when longer than a file name may be)."""
    b64 = urlsafe_b64encode(key.encode()).decode()
    parts = [b64[i : i + max_len - 1] for i in range(0, len(b64), max_len - 1)]
    parts = ["@" + p for p in parts[:-1]] + [parts[-1]]
    path = workdir / ".snakemake" / "incomplete" / Path(*parts)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")


def test_a_dead_runs_leftovers_are_cleaned(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    locks = tmp_path / ".snakemake" / "locks"
    locks.mkdir(parents=True)
    (locks / "0.input.lock").write_text("x\n")
    (locks / "0.output.lock").write_text("y\n")
    short = Path("results/s/textures/wall/texture.png")
    long = Path("results/s/" + "/".join(["a" * 60] * 4) + "/texture.png")  # marker name > 255 bytes
    for out in (short, long):
        (tmp_path / out).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / out).write_bytes(b"half")
        _mark_incomplete(tmp_path, str(out))
    kept = tmp_path / "results/s/textures/other/texture.png"
    kept.parent.mkdir(parents=True)
    kept.write_bytes(b"done")
    temp = tmp_path / "results/s/textures/other/.texture.abc123.part.png"
    temp.write_bytes(b"half")

    runguard.RunGuard("results/s", workdir=tmp_path).acquire()
    assert not any(locks.glob("*.lock"))
    assert not (tmp_path / short).exists() and not (tmp_path / long).exists()
    assert not any(p.is_file() for p in (tmp_path / ".snakemake" / "incomplete").rglob("*"))
    assert kept.read_bytes() == b"done" and not temp.exists()
    assert "removed its locks and 2 incomplete output(s)" in capsys.readouterr().err


def test_unwritable_results_stop_with_one_line(tmp_path, monkeypatch, capsys):
    from tests.breakage import make_unwritable

    monkeypatch.chdir(tmp_path)
    undo = make_unwritable(tmp_path / "results")
    if undo is None:
        pytest.skip("cannot make a folder read-only here")
    try:
        with pytest.raises(SystemExit):
            runguard.RunGuard("results/s", workdir=tmp_path).acquire()
    finally:
        undo()
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [e for e in err if e.startswith("difftex: error: results/s: ")] and len(err) == 1


def test_job_error_lines(tmp_path):
    log = tmp_path / "a.log"
    log.write_text("loading\ndifftex: warning: w\ndifftex: error: x.png: broken\n")
    assert runlog.job_error([log], "filter") == "difftex: error: x.png: broken"
    log.write_text("step 1\nKilled\n")  # no error line: the log's last line, and which job
    assert (
        runlog.job_error([log], "texture", "pid=wall")
        == f"difftex: error: {log}: job texture (pid=wall) failed: Killed"
    )
    log.write_text("")
    assert "empty log" in runlog.job_error([log], "texture")
    assert "has no log" in runlog.job_error([], "report")


def test_failure_report_ends_with_the_errors_and_merges_repeats(tmp_path):
    logs = []
    for i, msg in enumerate(
        ["difftex: error: S/proxy.obj: bad", "difftex: error: S/proxy.obj: bad", "difftex: error: y: other"]
    ):
        logs.append(tmp_path / "logs" / f"{i}.log")
        logs[-1].parent.mkdir(exist_ok=True)
        logs[-1].write_text(f"difftex: warning: S/images: note\n{msg}\n")
    jobs = [("texture", f"pid=p{i}", [str(p)]) for i, p in enumerate(logs)]
    lines = runlog.failure_report(jobs, tmp_path)
    assert lines[0] == "difftex: warning: S/images: note"  # warnings once, first
    assert lines[1].startswith("difftex: 3 jobs failed; logs: ")
    assert lines[2:] == ["difftex: error: S/proxy.obj: bad (in 2 jobs)", "difftex: error: y: other"]


def test_job_error_names_a_full_disk_when_the_log_ended_normally(tmp_path, monkeypatch):
    import collections

    log = tmp_path / "wall.log"
    log.write_text("texture wall: 49x64 texels, 3 photos read\n")
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(runlog.shutil, "disk_usage", lambda p: usage(10 << 20, 10 << 20, 0))
    line = runlog.job_error([log], "texture", "pid=wall")
    assert line.startswith("difftex: error: ") and "No space left on device" in line
    monkeypatch.setattr(runlog.shutil, "disk_usage", lambda p: usage(10 << 30, 1 << 30, 9 << 30))
    assert "49x64 texels" in runlog.job_error([log], "texture", "pid=wall")


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    # SIGINT back to its default in the child: a shell's background job (CI under nohup ... &)
    # starts with it ignored, and Python then keeps it ignored
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, timeout=120,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def test_ctrl_c_outside_the_scheduler_ends_with_one_line_and_status_130(tmp_path):
    """A KeyboardInterrupt that reaches the top level (Ctrl-C while Snakemake reads the Snakefile,
    say) ends the process with the interrupted line and 130: no traceback, no death by SIGINT
    (-2). Installing twice is harmless, and other errors keep their traceback and status."""
    head = "import os, signal, time\nfrom difftex.workflow import runguard\n"
    head += "runguard.exit_on_interrupt(); runguard.exit_on_interrupt()\n"
    for cause in ("raise KeyboardInterrupt", "os.kill(os.getpid(), signal.SIGINT); time.sleep(30)"):
        r = _python(head + "print('before')\n" + cause, tmp_path)
        assert r.returncode == runguard.INTERRUPTED_STATUS == 130, r.stderr
        assert r.stderr.splitlines() == [runguard.INTERRUPTED_LINE] and r.stdout == "before\n"
    r = _python(head + "raise ValueError('not an interrupt')", tmp_path)
    assert r.returncode == 1 and "Traceback" in r.stderr and "ValueError: not an interrupt" in r.stderr


def test_ctrl_c_after_the_run_ended_is_ignored(tmp_path):
    """Once onsuccess/onerror has run (``finished``), a Ctrl-C while the summary prints or the
    threads are joined neither raises nor counts as an interruption; before it, it does both."""
    code = (
        "import os, signal, time\nfrom difftex.workflow import runguard\n"
        "g = runguard.RunGuard('results/s', workdir='.')\ng._note_interrupts()\n"
        "g.finished = {finished}\n"
        "try:\n    os.kill(os.getpid(), signal.SIGINT); time.sleep(0.5)\n"
        "except KeyboardInterrupt:\n    print('raised')\n"
        "print('interrupted', g.interrupted)\n"
    )
    assert _python(code.format(finished=True), tmp_path).stdout.splitlines() == ["interrupted False"]
    assert _python(code.format(finished=False), tmp_path).stdout.splitlines() == ["raised", "interrupted True"]
