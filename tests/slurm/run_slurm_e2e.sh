#!/usr/bin/env bash
# End-to-end test of the SLURM profile on a throw-away single-node SLURM cluster.
#
#   bash tests/slurm/run_slurm_e2e.sh                 # tiny fan-out workflow (tests/slurm/Snakefile)
#   bash tests/slurm/run_slurm_e2e.sh --block         # the 100-polygon block (`difftex synth --preset
#                                                     # city-block`, preset=fast): once through SLURM, once
#                                                     # locally, textures must be byte-identical (~5 min
#                                                     # on 2 cores); docs/cluster.md gives its figures
#   bash tests/slurm/run_slurm_e2e.sh --real          # difftex Snakefile on `difftex synth --preset tiny`,
#                                                     # once through SLURM, once locally, textures compared
#                                                     # (tests/slurm/compare_outputs.py); add
#                                                     # --config preset=fast for a shorter run
#   bash tests/slurm/run_slurm_e2e.sh --snakefile F [--target T] [--config K=V ...] [--configfile C]
#
# Steps: install the Debian packages if missing (apt-get, needs root), write a slurm.conf
# for this machine (`slurmd -C`), start munged, slurmctld, slurmd, wait for the node to be
# idle, run snakemake with workflow/profiles/slurm, check the results, and stop every daemon
# it started in an EXIT trap (also on failure or Ctrl-C).
#
# No accounting daemon: the cluster uses AccountingStorageType=accounting_storage/none, where
# `sacct` cannot answer, so snakemake polls with `squeue` (--slurm-status-command squeue) and
# MinJobAge keeps finished jobs visible to squeue long enough. See docs/cluster.md.
#
# Options:
#   --real               run the real difftex workflow (needs ./Snakefile and `difftex synth`)
#   --block              --real on the 100-polygon block: generates `difftex synth --preset
#                        city-block` (unless --scene), preset=fast, --tolerance 0 (texture PNGs
#                        byte-identical); --config/--scene/--tolerance still apply
#   --snakefile F        Snakefile to run (default tests/slurm/Snakefile)
#   --target T           target file/rule (repeatable; default: the workflow's default target);
#                        with --real e.g. results/tiny/visibility/summary.json to stop early
#   --config K=V         passed to snakemake --config (repeatable)
#   --configfile C       passed to snakemake --configfile
#   --scene DIR          --real: use this scene instead of generating `difftex synth --preset tiny`
#   --tolerance X        --real: max allowed abs difference of texture values in [0,1] (default 0.02;
#                        --block: 0); 0 = the texture PNG files byte-identical, NPZ arrays equal
#   --workdir DIR        the runs go to DIR/slurm and DIR/local (DIR must not hold them yet) instead
#                        of a temporary folder, and DIR is kept
#   --summary FILE       --real: write the figures (walls, SLURM jobs, comparison, machine, commit)
#                        as JSON to FILE
#   --keep               keep the work directory and the cluster logs
#   --timeout S          give up on the snakemake run after S seconds (default 1800)
#   -- ARGS...           further snakemake arguments for every run (e.g. -- --groups ...)
#
# --real runs both workflows with the same job grouping and threads, so that their textures can
# be compared exactly: run.pack_jobs is fixed at 4 for both (its `auto` is the cores in a local
# run but 4 on a cluster), and both cap threads at the node's CPUs (--max-threads for SLURM,
# --cores for the local run). Give --config 'run={pack_jobs: N}' to pin another value.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
MODE=tiny
SNAKEFILE=""
TARGETS=()
CONFIG=()
CONFIGFILES=()
SCENE=""
EXTRA=()
TOLERANCE=""
KEEP=0
BLOCK=0
WORKDIR=""
SUMMARY=""
RUN_TIMEOUT=1800
COMMAND_LINE="bash tests/slurm/run_slurm_e2e.sh"
for a in "$@"; do  # as typed, for --summary: an argument with spaces or braces in single quotes
    if [[ "$a" =~ ^[A-Za-z0-9_./=:,+@%-]+$ ]]; then COMMAND_LINE+=" $a"; else COMMAND_LINE+=" '$a'"; fi
done

while [[ $# -gt 0 ]]; do
    case "$1" in
        --real) MODE=real ;;
        --block) MODE=real; BLOCK=1 ;;
        --snakefile) SNAKEFILE="$(realpath "$2")"; MODE=custom; shift ;;
        --target) TARGETS+=("$2"); shift ;;
        --config) CONFIG+=("$2"); shift ;;
        --configfile) CONFIGFILES+=("$(realpath "$2")"); shift ;;
        --tolerance) TOLERANCE="$2"; shift ;;
        --scene) SCENE="$(realpath "$2")"; shift ;;
        --workdir) WORKDIR="$(realpath -m "$2")"; shift ;;
        --summary) SUMMARY="$(realpath -m "$2")"; shift ;;
        --keep) KEEP=1 ;;
        --timeout) RUN_TIMEOUT="$2"; shift ;;
        --) shift; EXTRA=("$@"); break ;;
        -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "run_slurm_e2e.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
    esac
    shift
done

if [[ -z "$TOLERANCE" ]]; then
    TOLERANCE=0.02
    [[ $BLOCK -eq 1 ]] && TOLERANCE=0
fi

log() { printf '[slurm-e2e %s] %s\n' "$(date -u +%H:%M:%S)" "$*" >&2; }
die() { log "FAIL: $*"; exit 1; }
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

if [[ -f "$REPO/.venv/bin/activate" && -z "${VIRTUAL_ENV:-}" ]]; then
    # shellcheck disable=SC1091
    . "$REPO/.venv/bin/activate"
fi
command -v snakemake >/dev/null || die "snakemake not on PATH (activate the project's venv)"

T_TOTAL=$(now)

# --- 1. Debian packages --------------------------------------------------------------
# slurmctld + slurmd + slurm-client (sbatch/squeue/sinfo/scontrol) + munge (authentication).
# No slurmdbd/MariaDB: squeue is enough for snakemake's status polling (see header).
PACKAGES=(slurmctld slurmd slurm-client munge)
T_INSTALL=$(now)
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    SUDO=""
    [[ $(id -u) -eq 0 ]] || SUDO="sudo"
    log "installing ${PACKAGES[*]} (apt-get)"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${PACKAGES[@]}" >/dev/null
fi
INSTALL_S=$(elapsed "$T_INSTALL")
[[ $(id -u) -eq 0 ]] || die "the test cluster's daemons must be started as root"

# --- 2. cluster state + cleanup trap --------------------------------------------------
STATE="$(mktemp -d /tmp/difftex-slurm.XXXXXX)"
if [[ -n "$WORKDIR" ]]; then
    # the SLURM jobs run as root on this node: any local folder will do
    for d in slurm local; do
        [[ ! -e "$WORKDIR/$d" ]] || { rm -rf "$STATE"; die "--workdir $WORKDIR already holds $d/ (remove it or pick another folder)"; }
    done
    mkdir -p "$WORKDIR"
    WORK="$WORKDIR"
else
    WORK="$(mktemp -d /tmp/difftex-slurm-work.XXXXXX)"
fi
chmod 755 "$STATE" "$WORK"
# The config must sit at the default path: the plugin's job step strips SLURM_* variables
# (SLURM_CONF included) before it calls srun inside the job. An existing one is put back
# by the trap.
SLURM_CONF_FILE=/etc/slurm/slurm.conf
unset SLURM_CONF_BACKUP
# A job inherits the submitting shell's environment (--export=ALL): make sure no stale
# SLURM_* from an enclosing allocation leaks into the test.
unset SLURM_CONF SLURM_JOB_ID SLURM_JOBID SLURM_PARTITION SLURM_ACCOUNT || true
STARTED_MUNGE=0
STARTED_PIDS=()   # daemons this script started (checked to be gone on exit)
SMK_PID=""
T_SHUTDOWN=""

stop_pidfile() {  # stop the daemon whose pid is in $1, wait up to 10 s, then SIGKILL
    local pf="$1" pid
    [[ -s "$pf" ]] || return 0
    pid="$(cat "$pf")"
    kill -0 "$pid" 2>/dev/null || return 0
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.2; done
    kill -9 "$pid" 2>/dev/null || true
}

cleanup() {
    local rc=$?
    T_SHUTDOWN=$(now)
    set +e
    if [[ -n "${SMK_PID:-}" ]] && kill -0 "$SMK_PID" 2>/dev/null; then
        # INT, not TERM: on TERM snakemake waits for its running jobs to finish, on INT it
        # cancels them (scancel) and exits (`timeout` passes the signal on)
        kill -INT "$SMK_PID" 2>/dev/null
        for _ in $(seq 300); do kill -0 "$SMK_PID" 2>/dev/null || break; sleep 0.2; done
        kill -KILL "$SMK_PID" 2>/dev/null
        wait "$SMK_PID" 2>/dev/null
        log "snakemake interrupted; SLURM jobs left: $(squeue -h -o '%i %T' 2>/dev/null | tr '\n' ' ')"
    fi
    if [[ -s "$STATE/slurmctld.pid" ]]; then
        # cancel anything still queued, then stop both daemons
        scancel --full --quiet --partition=cpu,gpu 2>/dev/null
        stop_pidfile "$STATE/slurmd.pid"
        stop_pidfile "$STATE/slurmctld.pid"
    fi
    if [[ -n "${SLURM_CONF_BACKUP:-}" ]]; then
        mv -f "$SLURM_CONF_BACKUP" "$SLURM_CONF_FILE"
    elif grep -qs 'written by tests/slurm/run_slurm_e2e.sh' "$SLURM_CONF_FILE"; then
        rm -f "$SLURM_CONF_FILE"
    fi
    if [[ $STARTED_MUNGE -eq 1 ]]; then
        stop_pidfile "$STATE/munge/munged.pid"
    fi
    local pid left=()
    for pid in "${STARTED_PIDS[@]}"; do
        kill -0 "$pid" 2>/dev/null && left+=("$pid $(tr '\0' ' ' < "/proc/$pid/cmdline" 2>/dev/null)")
    done
    if [[ ${#left[@]} -gt 0 ]]; then
        log "WARNING: still running after the shutdown: ${left[*]}"
        [[ $rc -ne 0 ]] || rc=1
    fi
    log "cluster stopped in $(elapsed "$T_SHUTDOWN") s"
    if [[ $rc -ne 0 ]]; then
        for f in "$STATE"/slurmctld.log "$STATE"/slurmd.log; do
            [[ -f "$f" ]] && { log "--- tail of $f"; tail -n 20 "$f" >&2; }
        done
        find "$WORK" -path '*slurm_logs*' -name '*.log' 2>/dev/null | head -n 3 | while read -r f; do
            log "--- tail of $f"; tail -n 20 "$f" >&2
        done
    fi
    if [[ $KEEP -eq 1 ]]; then
        log "kept: cluster state $STATE, work dir $WORK"
    elif [[ -n "$WORKDIR" ]]; then
        rm -rf "$STATE"
        log "kept: work dir $WORK (--workdir)"
    else
        rm -rf "$STATE" "$WORK"
    fi
    log "total $(elapsed "$T_TOTAL") s (install ${INSTALL_S} s, cluster start ${START_S:-?} s, run ${RUN_S:-?} s), exit $rc"
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# --- 3. munge -------------------------------------------------------------------------
T_START=$(now)
if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    log "using the munged already running"
else
    [[ -s /etc/munge/munge.key ]] || { log "creating /etc/munge/munge.key"; mungekey --create --force; }
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
    install -d -o munge -g munge -m 755 /run/munge
    install -d -o munge -g munge -m 700 /var/log/munge /var/lib/munge
    install -d -o munge -g munge -m 700 "$STATE/munge"
    runuser -u munge -- munged --pid-file="$STATE/munge/munged.pid" --log-file="$STATE/munge/munged.log"
    STARTED_MUNGE=1
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.1; done
    [[ -s "$STATE/munge/munged.pid" ]] && STARTED_PIDS+=("$(cat "$STATE/munge/munged.pid")")
    munge -n | unmunge >/dev/null || die "munged does not answer"
fi

# --- 4. slurm.conf for this one machine -------------------------------------------------
HOST="$(hostname -s)"
NODE_LINE="$(slurmd -C | head -n 1)"   # NodeName=<host> CPUs=.. ... RealMemory=..
[[ "$NODE_LINE" == NodeName=* ]] || die "slurmd -C printed no node line: $NODE_LINE"
NODE_CPUS="$(grep -o 'CPUs=[0-9]*' <<<"$NODE_LINE" | cut -d= -f2)"
mkdir -p "$STATE/ctld" "$STATE/slurmd" "$(dirname "$SLURM_CONF_FILE")"
if [[ -e "$SLURM_CONF_FILE" ]] && ! grep -qs 'written by tests/slurm/run_slurm_e2e.sh' "$SLURM_CONF_FILE"; then
    SLURM_CONF_BACKUP="$STATE/slurm.conf.orig"
    cp -p "$SLURM_CONF_FILE" "$SLURM_CONF_BACKUP"
    log "moved the existing $SLURM_CONF_FILE aside; it is restored on exit"
fi
cat > "$SLURM_CONF_FILE" <<EOF
# single-node test cluster written by tests/slurm/run_slurm_e2e.sh
ClusterName=difftex-e2e
SlurmctldHost=$HOST
# unusual ports so that a real cluster daemon on this machine is not disturbed
SlurmctldPort=16817
SlurmdPort=16818
AuthType=auth/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/slurmd
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
# containers (gVisor, docker) have no usable cgroups: track processes via /proc
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
# no slurmdbd: sacct cannot answer, snakemake polls with squeue instead
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
# finished jobs stay visible to 'squeue --states=all' for 10 minutes; the plugin only
# trusts squeue when MinJobAge >= 3 x its first status-check delay
MinJobAge=600
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
InactiveLimit=0
KillWait=5
Waittime=0
$NODE_LINE State=UNKNOWN
# partition names match workflow/profiles/slurm/partitions.yaml; this machine has no GPU,
# the gpu partition only exists so that the profile's partition file is valid here
PartitionName=cpu Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$HOST Default=NO MaxTime=INFINITE State=UP
EOF

slurmctld -c -f "$SLURM_CONF_FILE" || die "slurmctld did not start (see $STATE/slurmctld.log)"
slurmd -f "$SLURM_CONF_FILE" || die "slurmd did not start (see $STATE/slurmd.log)"
for pf in slurmctld slurmd; do
    for _ in $(seq 50); do [[ -s "$STATE/$pf.pid" ]] && break; sleep 0.1; done
    [[ -s "$STATE/$pf.pid" ]] && STARTED_PIDS+=("$(cat "$STATE/$pf.pid")")
done
state=""
for _ in $(seq 120); do
    state="$(sinfo -h -N -n "$HOST" -p cpu -o '%T' 2>/dev/null | head -n 1 || true)"
    [[ "$state" == idle ]] && break
    sleep 0.5
done
[[ "$state" == idle ]] || die "node $HOST not idle after 60 s (state '$state')"
START_S=$(elapsed "$T_START")
log "cluster up in ${START_S} s: $(sinfo -h -o '%P %D %c cpus %m MB %T' | tr '\n' ';')"

# --- 5. run ---------------------------------------------------------------------------
# Settings that only make sense on this toy cluster are given on the command line, so that
# the profile itself stays the one a user runs on a real cluster:
#   squeue polling (no accounting db), a first status check after 5 s instead of 40 s,
#   no shared-filesystem latency, and no rule asking for more threads than this node has.
SLURM_ARGS=(
    --profile "$REPO/workflow/profiles/slurm"
    --max-threads "$NODE_CPUS"
    --slurm-status-command squeue
    --slurm-init-seconds-before-status-checks 5
    --latency-wait 5
    --slurm-keep-successful-logs
)

run_snakemake() {  # run_snakemake <workdir> <profile args...> -- <snakemake args...>
    local dir="$1"; shift
    mkdir -p "$dir"
    # in the background + wait, so that a TERM/INT to this script reaches the trap at once
    # (bash defers traps while a foreground child runs); the trap then stops snakemake
    (cd "$dir" && exec timeout "$RUN_TIMEOUT" snakemake "${EXTRA[@]}" "$@") > "$dir/snakemake.out" 2>&1 &
    SMK_PID=$!
    local rc=0 stuck
    while kill -0 "$SMK_PID" 2>/dev/null; do
        # a job this cluster can never run (more cpus/memory/time than the node or partition
        # has) would stay pending until the timeout: fail at once instead
        stuck=$(squeue -h -t PD -o '%i %r' 2>/dev/null \
            | grep -E 'PartitionConfig|PartitionNodeLimit|PartitionTimeLimit|BadConstraints|ReqNodeNotAvail' || true)
        [[ -z "$stuck" ]] || die "a SLURM job can never start on this cluster: $stuck ($(scontrol show job -o "${stuck%% *}" | grep -o 'NumCPUs=[^ ]* .*MinMemoryNode=[^ ]*'))"
        sleep 2
    done
    wait "$SMK_PID" || rc=$?
    SMK_PID=""
    [[ $rc -eq 0 ]] || { tail -n 40 "$dir/snakemake.out" >&2; return 1; }
}

steps() {  # the number of jobs a finished snakemake run ran, from its last "N of M steps" line
    { grep -oE '[0-9]+ of [0-9]+ steps' "$1" || echo "0 of 0 steps"; } | tail -n 1 | awk '{print $3}'
}

check_tiny() {  # the tiny workflow's results: every job ran as its own SLURM job
    local dir="$1" summary="$1/summary.txt"
    [[ -s "$summary" ]] || die "no $summary"
    local n_poly n_jobs
    n_poly=$(grep -c '^poly=' "$summary" || true)
    [[ $n_poly -eq 2 ]] || die "expected 2 per-polygon lines in summary.txt, got $n_poly"
    grep -q '^gather ' "$summary" || die "no gather line in summary.txt"
    if grep -q 'slurm_job=none' "$summary"; then die "a job did not run under SLURM: $(cat "$summary")"; fi
    n_jobs=$(grep -o 'slurm_job=[0-9]*' "$summary" | sort -u | wc -l)
    [[ $n_jobs -eq 3 ]] || die "expected 3 distinct SLURM job ids, got $n_jobs"
    # threads -> --cpus-per-task, mem_mb -> --mem, runtime -> -t, as SLURM saw them
    # (the job's own environment is no witness: the plugin strips SLURM_* inside the job)
    local line id rule want_cpus want_mem info
    while read -r line; do
        id=$(grep -o 'slurm_job=[0-9]*' <<<"$line" | cut -d= -f2)
        rule=per_polygon; want_cpus=1; want_mem=200M
        [[ "$line" == gather* ]] && { rule=gather; want_cpus=2; want_mem=300M; }
        info=$(scontrol show job -o "$id")
        grep -q "NumCPUs=$want_cpus " <<<"$info" || die "$rule job $id: expected NumCPUs=$want_cpus: $info"
        grep -q "MinMemoryNode=$want_mem " <<<"$info" || die "$rule job $id: expected MinMemoryNode=$want_mem: $info"
        grep -q "TimeLimit=00:05:00 " <<<"$info" || die "$rule job $id: expected TimeLimit=00:05:00: $info"
        grep -q "Partition=cpu " <<<"$info" || die "$rule job $id: expected Partition=cpu: $info"
        grep -q "JobState=COMPLETED " <<<"$info" || die "$rule job $id: not COMPLETED: $info"
    done < "$summary"
    local listed
    listed=$(squeue -h --states=all -o '%i %T' | grep -c COMPLETED || true)
    [[ $listed -ge 3 ]] || die "squeue lists $listed completed jobs, expected >= 3"
    log "tiny workflow OK: 3 SLURM jobs in partition cpu, threads/mem_mb/runtime passed through"
    sed 's/^/    /' "$summary" >&2
}

T_RUN=$(now)
case "$MODE" in
    tiny)
        log "running the tiny fan-out workflow through SLURM in $WORK/slurm"
        run_snakemake "$WORK/slurm" "${SLURM_ARGS[@]}" -s "$REPO/tests/slurm/Snakefile" \
            --config 'polys=["p0","p1"]' \
            || die "snakemake failed (log: $WORK/slurm/snakemake.out)"
        check_tiny "$WORK/slurm"
        ;;
    custom)
        args=(-s "$SNAKEFILE")
        [[ ${#CONFIGFILES[@]} -gt 0 ]] && args+=(--configfile "${CONFIGFILES[@]}")
        [[ ${#CONFIG[@]} -gt 0 ]] && args+=(--config "${CONFIG[@]}")
        log "running $SNAKEFILE ${TARGETS[*]:-} through SLURM in $WORK/slurm"
        run_snakemake "$WORK/slurm" "${SLURM_ARGS[@]}" "${args[@]}" -- "${TARGETS[@]}" \
            || die "snakemake failed (log: $WORK/slurm/snakemake.out)"
        for t in "${TARGETS[@]}"; do
            # a target that is a file must exist afterwards; a rule name is checked by the exit code
            if [[ "$t" == */* || "$t" == *.* ]]; then [[ -e "$WORK/slurm/$t" || -e "$t" ]] || die "target $t missing"; fi
        done
        log "custom workflow OK"
        ;;
    real)
        [[ -f "$REPO/Snakefile" ]] || die "no $REPO/Snakefile yet: the real workflow is not written"
        difftex synth --help >/dev/null 2>&1 || die "'difftex synth' is not available"
        PRESET=tiny
        [[ $BLOCK -eq 1 ]] && PRESET=city-block
        T_SYNTH=$(now)
        if [[ -n "$SCENE" ]]; then
            [[ -d "$SCENE" ]] || die "--scene $SCENE: no such folder"
            log "using the scene $SCENE"
        else
            SCENE="$WORK/$PRESET"
            log "writing the $PRESET synthetic scene to $SCENE"
            difftex synth --preset "$PRESET" --out "$SCENE" > "$WORK/synth.out" 2>&1 \
                || { tail -n 20 "$WORK/synth.out" >&2; die "difftex synth failed"; }
            log "scene written in $(elapsed "$T_SYNTH") s: $(tail -n 1 "$WORK/synth.out")"
        fi
        SYNTH_S=$(elapsed "$T_SYNTH")
        # Both runs group the texture jobs alike: run.pack_jobs `auto` is the cores of a local run
        # but 4 on a cluster. A --configfile below the --config values, which can still change it
        # (deep-merged: --config 'run={evaluate: false}' keeps this pack_jobs).
        {
            echo "# written by tests/slurm/run_slurm_e2e.sh: the same texture jobs in both runs"
            [[ $BLOCK -eq 1 ]] && echo "preset: fast"
            echo "run:"
            echo "  pack_jobs: 4"
        } > "$WORK/e2e_config.yaml"
        # config/config.yaml is read by the workflow itself; it is not passed as --configfile,
        # which would rank it above the chosen preset
        args=(-s "$REPO/Snakefile" --configfile "$WORK/e2e_config.yaml" "${CONFIGFILES[@]}")
        args+=(--config "scene=$SCENE" "${CONFIG[@]}")
        log "real workflow through SLURM in $WORK/slurm (config: $(grep -v '^#' "$WORK/e2e_config.yaml" | tr '\n' ' ')${CONFIG[*]:++ ${CONFIG[*]}})"
        T_SLURM=$(now)
        run_snakemake "$WORK/slurm" "${SLURM_ARGS[@]}" "${args[@]}" -- "${TARGETS[@]}" \
            || die "snakemake (slurm) failed (log: $WORK/slurm/snakemake.out)"
        SLURM_RUN_S=$(elapsed "$T_SLURM")
        # every sbatch: "Job N has been submitted with SLURM jobid M (log: .../rule_<rule>/...)"
        grep -o 'submitted with SLURM jobid [0-9]* (log: [^)]*)' "$WORK/slurm/snakemake.out" \
            > "$WORK/sbatch.txt" || true
        n_sbatch=$(wc -l < "$WORK/sbatch.txt")
        [[ $n_sbatch -gt 0 ]] || die "no SLURM job was submitted: the run did not go through SLURM"
        per_rule=$(grep -o 'slurm_logs/rule_[A-Za-z0-9_]*' "$WORK/sbatch.txt" | sed 's|slurm_logs/rule_||' \
            | sort | uniq -c | awk '{printf "%s%s %s", (NR>1 ? ", " : ""), $1, $2}')
        # all jobs of the run ("N of N steps (100%) done"); those not submitted ran on this host
        # (localrules: finish, report, the stage configs, all)
        n_steps=$(steps "$WORK/slurm/snakemake.out")
        n_local_rules=$((n_steps - n_sbatch))
        # what SLURM recorded of each job (finished jobs stay listed MinJobAge = 600 s)
        for id in $(grep -o 'jobid [0-9]*' "$WORK/sbatch.txt" | cut -d' ' -f2); do
            scontrol show job -o "$id" 2>/dev/null || echo "JobId=$id (no longer listed)"
        done > "$WORK/slurm_jobs.txt"
        n_done=$(grep -c 'JobState=COMPLETED ' "$WORK/slurm_jobs.txt" || true)
        log "slurm run done in ${SLURM_RUN_S} s: $n_sbatch SLURM jobs ($per_rule; $n_done COMPLETED), $n_local_rules of its $n_steps jobs ran on the submit host"
        log "same workflow with the local profile in $WORK/local"
        T_LOCAL=$(now)
        run_snakemake "$WORK/local" --profile "$REPO/workflow/profiles/local" --cores "$NODE_CPUS" "${args[@]}" -- "${TARGETS[@]}" \
            || die "snakemake (local) failed (log: $WORK/local/snakemake.out)"
        LOCAL_RUN_S=$(elapsed "$T_LOCAL")
        n_local_jobs=$(steps "$WORK/local/snakemake.out")
        log "local run done in ${LOCAL_RUN_S} s ($n_local_jobs jobs)"
        partial=()
        [[ ${#TARGETS[@]} -gt 0 ]] && partial=(--partial)
        cmp_rc=0
        python "$REPO/tests/slurm/compare_outputs.py" "$WORK/slurm" "$WORK/local" --tolerance "$TOLERANCE" "${partial[@]}" \
            > "$WORK/compare.out" 2>&1 || cmp_rc=$?
        sed 's/^/    /' "$WORK/compare.out" >&2
        if [[ -n "$SUMMARY" ]]; then
            mkdir -p "$(dirname "$SUMMARY")"
            SUMMARY_COMMAND="$COMMAND_LINE" SUMMARY_WORK="$WORK" SUMMARY_SCENE="$SCENE" SUMMARY_REPO="$REPO" \
            SUMMARY_SLURM_S="$SLURM_RUN_S" SUMMARY_LOCAL_S="$LOCAL_RUN_S" SUMMARY_SYNTH_S="$SYNTH_S" \
            SUMMARY_START_S="$START_S" SUMMARY_NODE="$NODE_LINE" SUMMARY_TOL="$TOLERANCE" \
            SUMMARY_CMP_RC="$cmp_rc" SUMMARY_LOCAL_JOBS="$n_local_jobs" SUMMARY_LOCAL_RULES="$n_local_rules" SUMMARY_STEPS="$n_steps" \
            python - "$SUMMARY" <<'PY'
import json, os, platform, re, subprocess, sys
from datetime import datetime, timezone
from pathlib import Path

e = os.environ
work = Path(e["SUMMARY_WORK"])
def sh(*cmd):
    try:
        return subprocess.run(cmd, capture_output=True, text=True, cwd=e["SUMMARY_REPO"]).stdout.strip()
    except OSError:
        return ""
def seconds(t):  # [D-]HH:MM:SS
    d, _, hms = t.rpartition("-")
    h, m, s_ = (int(x) for x in hms.split(":"))
    return (int(d) if d else 0) * 86400 + h * 3600 + m * 60 + s_
jobs = []
for line in (work / "slurm_jobs.txt").read_text().splitlines():
    f = dict(kv.split("=", 1) for kv in line.split() if "=" in kv)
    if "RunTime" in f:
        jobs.append({"id": int(f["JobId"]), "name": f.get("JobName"), "state": f.get("JobState"),
                     "cpus": int(f.get("NumCPUs", 0)), "mem": f.get("MinMemoryNode"),
                     "partition": f.get("Partition"), "run_s": seconds(f["RunTime"])})
sbatch = (work / "sbatch.txt").read_text().splitlines()
rules = {}
for line in sbatch:
    m = re.search(r"slurm_logs/rule_([A-Za-z0-9_]+)", line)
    rules[m.group(1) if m else "?"] = rules.get(m.group(1) if m else "?", 0) + 1
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "")
mem = next((int(l.split()[1]) // 1024 for l in open("/proc/meminfo") if l.startswith("MemTotal")), 0)
out = {
    "command": e["SUMMARY_COMMAND"],
    "date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    "git_commit": sh("git", "rev-parse", "--short", "HEAD"),
    "git_dirty": bool(sh("git", "status", "--porcelain", "--untracked-files=no")),
    "machine": {"cpu": cpu, "cpus": os.cpu_count(), "mem_mb": mem, "kernel": platform.release(),
                "os": next((l.split("=", 1)[1].strip().strip('"') for l in open("/etc/os-release")
                            if l.startswith("PRETTY_NAME=")), ""),
                "slurm": sh("slurmd", "-V"), "snakemake": sh("snakemake", "--version"),
                "node": e["SUMMARY_NODE"]},
    "scene": e["SUMMARY_SCENE"],
    "scene_s": float(e["SUMMARY_SYNTH_S"]),
    "cluster_start_s": float(e["SUMMARY_START_S"]),
    "slurm_run_s": float(e["SUMMARY_SLURM_S"]),
    "local_run_s": float(e["SUMMARY_LOCAL_S"]),
    "slurm_jobs": len(sbatch),
    "slurm_jobs_per_rule": rules,
    "slurm_job_time_s": sum(j["run_s"] for j in jobs),
    "slurm_jobs_detail": jobs,
    "slurm_run_jobs": int(e["SUMMARY_STEPS"]),
    "slurm_run_local_jobs": int(e["SUMMARY_LOCAL_RULES"]),
    "local_run_jobs": int(e["SUMMARY_LOCAL_JOBS"]),
    "config": (work / "e2e_config.yaml").read_text(),
    "tolerance": float(e["SUMMARY_TOL"]),
    "comparison": (work / "compare.out").read_text().strip().splitlines(),
    "comparison_passed": e["SUMMARY_CMP_RC"] == "0",
}
Path(sys.argv[1]).write_text(json.dumps(out, indent=1) + "\n")
PY
            log "figures written to $SUMMARY"
        fi
        [[ $cmp_rc -eq 0 ]] || die "slurm and local outputs differ (tolerance $TOLERANCE)"
        ;;
esac
RUN_S=$(elapsed "$T_RUN")
log "PASS ($MODE)"
