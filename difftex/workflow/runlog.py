"""What the console shows at the end of a workflow run: the failed jobs' one-line errors and where
their logs are, and the warnings of the stages.

Every stage writes its output, and so its ``difftex: error:``/``difftex: warning:`` lines, to its
job's log (R/logs/...), where Snakemake's console does not show them. The Snakefile's onerror
and onsuccess handlers call these functions; they read log files only, so they work the same
for every executor (local, SLURM) as long as the logs are on a shared filesystem.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from difftex.errors import ERROR_PREFIX, WARNING_PREFIX, one_line
from difftex.layout import Results

INTERRUPTED_LINE = "difftex: interrupted; run the same command again to resume"
INTERRUPTED_STATUS = 130  # 128 + SIGINT, as a shell reports a job stopped by Ctrl-C

# a log's last lines hold its error; no need to read a long optimizer log whole
TAIL_BYTES = 64 * 1024


def _tail_lines(path: Path) -> list[str]:
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - TAIL_BYTES))
            text = f.read().decode("utf-8", errors="replace")
    except OSError:
        return []
    return [ln.strip() for ln in text.replace("\r", "\n").splitlines() if ln.strip()]


def job_error(logs: list[str | Path], rule: str, label: str = "") -> str:
    """The one error line of a failed job: its last ``difftex: error:`` line, else a line
    saying that the job failed with the last line of its log (a killed or crashed job).

    Args:
        logs: the job's log files.
        rule: its rule name, for the fallback line.
        label: its wildcards (e.g. the polygon id), for the fallback line.
    """
    last = ""
    for log in logs:
        lines = _tail_lines(Path(log))
        errors = [ln for ln in lines if ln.startswith(ERROR_PREFIX)]
        if errors:
            return errors[-1]
        if lines:
            last = lines[-1]
    what = f"job {rule}" + (f" ({label})" if label else "")
    if not logs:
        return ERROR_PREFIX + f"{what} failed (it has no log; see Snakemake's log)"
    tail = f": {one_line(last)[:300]}" if last else " with an empty log (killed? out of memory or time?)"
    if _disk_full(Path(logs[0]).parent):
        # the job's own code finished, then writing its outputs (or Snakemake's records of
        # them) failed: the last log line is a success message and would mislead
        tail = " after its log ended: No space left on device where its results go"
    return ERROR_PREFIX + f"{logs[0]}: {what} failed{tail}"


def _disk_full(folder: Path, reserve: int = 1 << 20) -> bool:
    """Whether the filesystem holding ``folder`` has less than ``reserve`` bytes free."""
    try:
        return shutil.disk_usage(folder).free < reserve
    except OSError:
        return False


def failed_jobs(workflow) -> list[tuple[str, str, list[str]]]:
    """(rule, wildcards, log files) of the jobs Snakemake's scheduler saw fail."""
    scheduler = getattr(workflow, "scheduler", None)
    jobs = sorted(getattr(scheduler, "failed", ()) or (), key=lambda j: str(getattr(j, "jobid", "")))
    out = []
    for job in jobs:
        rule = getattr(getattr(job, "rule", None), "name", "?")
        wildcards = ", ".join(f"{k}={v}" for k, v in dict(getattr(job, "wildcards_dict", {}) or {}).items())
        logs = [str(p) for p in (getattr(job, "log", None) or [])]
        out.append((rule, wildcards, logs))
    return out


def recent_error_logs(results: Path, since: float) -> list[tuple[str, str, list[str]]]:
    """Fallback when the scheduler's failed jobs are not available: logs under R/logs changed
    since ``since`` (epoch seconds) that hold an error line."""
    out = []
    root = Results(results).logs_dir
    if root.is_dir():
        for log in sorted(root.rglob("*.log")):
            try:
                if log.stat().st_mtime < since:
                    continue
            except OSError:
                continue
            if any(ln.startswith(ERROR_PREFIX) for ln in _tail_lines(log)):
                out.append((log.stem, "", [str(log)]))
    return out


def warnings(results: str | Path) -> list[str]:
    """The distinct ``difftex: warning:`` lines of the job logs under R/logs, in first-seen order
    (the logs of the jobs that made the current results, rerun or not)."""
    seen: dict[str, None] = {}
    root = Results(results).logs_dir
    if root.is_dir():
        for log in sorted(root.rglob("*.log")):
            try:
                text = log.read_text(errors="replace")
            except OSError:
                continue
            for ln in text.splitlines():
                ln = ln.strip()
                if ln.startswith(WARNING_PREFIX):
                    seen.setdefault(ln, None)
    return list(seen)


def failure_report(jobs: list[tuple[str, str, list[str]]], results: str | Path) -> list[str]:
    """The lines printed after a failed run, the last one being an error line.

    Identical error lines (the same bad input seen by several polygon jobs) are printed once.
    """
    lines = warnings(results)
    if not jobs:
        return [
            *lines,
            ERROR_PREFIX + "the run failed before any job could report why (see Snakemake's messages above)",
        ]
    errors: dict[str, list[str]] = {}
    logs: list[str] = []
    for rule, wildcards, job_logs in jobs:
        errors.setdefault(job_error(job_logs, rule, wildcards), []).append(rule)
        logs.extend(job_logs[:1])
    shown = ", ".join(logs[:3]) + (f" and {len(logs) - 3} more" if len(logs) > 3 else "")
    n = len(jobs)
    lines.append(f"difftex: {n} job{'s' if n > 1 else ''} failed; log{'s' if len(logs) > 1 else ''}: {shown or 'none'}")
    for err, rules in errors.items():
        lines.append(err + (f" (in {len(rules)} jobs)" if len(rules) > 1 else ""))
    return lines


def report_failure(workflow, results: str | Path, since: float, interrupted: bool = False) -> None:
    """The Snakefile's onerror handler: print the report on stderr and exit with status 1, so
    that the error line is the last line on the console (Snakemake would otherwise add its
    own lines after the handler's). After Ctrl-C: one line saying how to resume, status 130."""
    scheduler = getattr(workflow, "scheduler", None)
    if interrupted or getattr(scheduler, "_user_kill", None):
        print(INTERRUPTED_LINE, file=sys.stderr, flush=True)
        raise SystemExit(INTERRUPTED_STATUS)
    jobs = failed_jobs(workflow) or recent_error_logs(Path(results), since)
    print("\n".join(failure_report(jobs, results)), file=sys.stderr, flush=True)
    raise SystemExit(1)


def abnormal_end_report(results: str | Path, since: float, snakemake_error: str, workdir: Path) -> list[str]:
    """The lines printed when Snakemake stopped on an error of its own (no onerror): its message
    on one line, then the error lines of the jobs that failed in this run, the last one being
    an error line either way.

    Args:
        results: the results folder (its logs are read).
        since: the run's start (epoch seconds): older logs are not this run's.
        snakemake_error: the last error Snakemake logged (often several lines).
        workdir: the working directory, named when no job reported an error.
    """
    text = one_line(snakemake_error)
    for prefix in ("WorkflowError: ", "Error: "):
        text = text.removeprefix(prefix)
    text = text[:400]
    lines = warnings(results)
    jobs = recent_error_logs(Path(results), since)
    if not jobs:
        return [*lines, ERROR_PREFIX + f"{workdir}: Snakemake stopped: {text}"]
    lines.append(f"difftex: Snakemake stopped: {text}")
    errors = dict.fromkeys(job_error(logs, rule) for rule, _, logs in jobs)
    return [*lines, *errors]


def print_warnings(results: str | Path) -> None:
    """Part of the onsuccess message: the stages' warnings, once each."""
    lines = warnings(results)
    if lines:
        print("\n".join(lines), file=sys.stderr, flush=True)
