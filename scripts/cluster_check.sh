#!/usr/bin/env bash
# Prove that the pipeline runs on a real SLURM: set up a one-node SLURM cluster on this
# machine, run the main job on `synthtiny` through it (profiles/slurm, or
# profiles/slurm-generic), run the same locally, and require identical results.
#
#   bash scripts/cluster_check.sh [--executor slurm|generic] [--reference CACHE] [--keep]
#
#   --executor slurm    the SLURM executor plugin, profiles/slurm (default)
#   --executor generic  the cluster-generic plugin, profiles/slurm-generic
#                       (sbatch --parsable + scripts/slurm/status.py)
#   --reference CACHE   compare against the synthtiny results already in CACHE (a local
#                       run's FREEZE_CACHE) instead of running the local job here
#   --keep              keep the scratch folder (runs, logs) even on success
#
# Run as root on Debian 12 after scripts/install.sh; idempotent. It installs the Debian
# packages slurm-wlm and munge (and the two Snakemake executor plugins into .venv) if
# missing, writes a one-node slurm.conf under /var/lib/freeze-cluster-check (no
# systemd, no cgroups, no accounting database: proctrack/linuxproc, task/none,
# accounting_storage/none, job completions logged with jobcomp/filetxt), points
# /etc/slurm/slurm.conf at it for the length of the check, starts munged, slurmctld and
# slurmd directly, and stops them again on exit whatever happens (trap). Scratch goes
# to a fresh temp folder, removed on success unless --keep. One line per step; on a
# failure, one line `cluster_check: FAILED: ...` and exit 1.
set -euo pipefail
{ # the whole script is one block, read before it runs: editing it mid-check is harmless
cd "$(dirname "$0")/.."
ROOT="$PWD"

EXECUTOR=slurm
REFERENCE=""
KEEP=0
while [ $# -gt 0 ]; do
  case "$1" in
    --executor|--reference)
      [ $# -ge 2 ] || { echo "cluster_check: FAILED: $1 needs a value (see --help)" >&2; exit 2; }
      if [ "$1" = --executor ]; then EXECUTOR="$2"; else REFERENCE="$2"; fi; shift 2 ;;
    --executor=*) EXECUTOR="${1#*=}"; shift ;;
    --reference=*) REFERENCE="${1#*=}"; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "cluster_check: FAILED: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
case "$EXECUTOR" in slurm|generic) ;; *) echo "cluster_check: FAILED: --executor must be slurm or generic" >&2; exit 2 ;; esac

DATASET=synthtiny
BASE=/var/lib/freeze-cluster-check            # slurm.conf, state, spool, daemon logs, pid files
CONF="$BASE/etc/slurm.conf"
SYS_CONF=/etc/slurm/slurm.conf
PLUGINS="snakemake-executor-plugin-slurm==2.8.0 snakemake-executor-plugin-cluster-generic==1.0.9"
T0=$(date +%s)

step() { printf '[cluster_check %s] %s\n' "$(date +%H:%M:%S)" "$*"; }
fail() { echo "cluster_check: FAILED: $*" >&2; exit 1; }
elapsed() { echo $(( $(date +%s) - $1 )); }

[ "$(id -u)" -eq 0 ] || fail "run as root (it installs packages and starts the SLURM daemons)"
[ -x .venv/bin/python ] && [ -x .venv/bin/snakemake ] || fail "no .venv here: run scripts/install.sh first"

# ---------------------------------------------------------------- cleanup (always)
STARTED_MUNGE=0
STARTED_SLURM=0
LINKED_CONF=0
SCRATCH=""
OK=0

pid_of() {  # pid from a pid file, if that process is alive and is the named program
  local file="$1" name="$2" pid
  [ -f "$file" ] || return 1
  pid=$(tr -dc '0-9' < "$file")
  [ -n "$pid" ] && [ -r "/proc/$pid/comm" ] && [ "$(cat "/proc/$pid/comm")" = "$name" ] && echo "$pid"
}

stop_daemons() {  # stop_daemons NAME PIDFILE [NAME PIDFILE ...]: TERM all, wait up to 15 s, then KILL
  local pids="" files="" pid i
  while [ $# -ge 2 ]; do
    if pid=$(pid_of "$2" "$1"); then kill "$pid" 2>/dev/null || true; pids="$pids $pid"; fi
    files="$files $2"; shift 2
  done
  for i in $(seq 1 75); do
    local alive=""
    for pid in $pids; do [ -d "/proc/$pid" ] && alive="$alive $pid"; done
    pids="$alive"; [ -z "$pids" ] && break
    sleep 0.2
  done
  for pid in $pids; do kill -9 "$pid" 2>/dev/null || true; done
  # shellcheck disable=SC2086
  rm -f $files
}

cleanup() {
  local rc=$?
  trap - EXIT INT TERM
  if [ -n "${LOCAL_PID:-}" ] && kill -0 "$LOCAL_PID" 2>/dev/null; then  # the local run, on a failure
    pkill -TERM -P "$LOCAL_PID" 2>/dev/null || true; kill "$LOCAL_PID" 2>/dev/null || true; wait "$LOCAL_PID" 2>/dev/null || true
  fi
  stop_daemons slurmd "$BASE/run/slurmd.pid" slurmctld "$BASE/run/slurmctld.pid"
  if [ "$STARTED_MUNGE" = 1 ]; then stop_daemons munged /run/munge/munged.pid; rm -f "$BASE/run/munged.started-by-check"; fi
  # Leave no slurm.conf at the system path once the controller is gone: with one, every
  # `snakemake` start (the SLURM plugin asks `scontrol show config` when it loads)
  # would wait ~9 s for a controller that does not answer.
  if [ "$LINKED_CONF" = 1 ] && [ -L "$SYS_CONF" ]; then rm -f "$SYS_CONF"; fi
  if [ "$STARTED_SLURM" = 1 ]; then
    step "daemons stopped (slurmd, slurmctld$([ "$STARTED_MUNGE" = 1 ] && echo ', munged'))"
  fi
  if [ -n "$SCRATCH" ] && [ -d "$SCRATCH" ]; then
    if [ "$OK" = 1 ] && [ "$KEEP" = 0 ]; then rm -rf "$SCRATCH"; else step "scratch kept: $SCRATCH"; fi
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'echo "cluster_check: FAILED: interrupted" >&2; exit 130' INT TERM

# ---------------------------------------------------------------- 1. packages
t=$(date +%s)
missing=""
for p in slurm-wlm munge; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  step "installing Debian packages:$missing"
  apt-get update -qq >/dev/null || fail "apt-get update failed"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing >/dev/null 2>&1 \
    || fail "apt-get install$missing failed"
  step "Debian packages installed in $(elapsed "$t") s"
else
  step "Debian packages slurm-wlm and munge already installed"
fi
for cmd in sbatch squeue scontrol sinfo slurmctld slurmd munged; do
  command -v "$cmd" >/dev/null || fail "$cmd not found after installing slurm-wlm and munge"
done
if .venv/bin/python -c 'import snakemake_executor_plugin_slurm, snakemake_executor_plugin_cluster_generic' 2>/dev/null; then
  step "Snakemake executor plugins already in .venv"
else
  step "installing into .venv: $PLUGINS"
  # shellcheck disable=SC2086
  .venv/bin/python -m pip install -q --disable-pip-version-check $PLUGINS || fail "pip install of the executor plugins failed"
fi

# ---------------------------------------------------------------- 2. configuration
if [ -e "$SYS_CONF" ] || [ -L "$SYS_CONF" ]; then
  if [ "$(readlink "$SYS_CONF" 2>/dev/null)" != "$CONF" ]; then
    fail "$SYS_CONF exists and was not written by this check: this machine has its own SLURM; refusing to touch it"
  fi
fi
for d in slurmctld slurmd; do
  # a daemon of ours left by a killed check is restarted below; any other is not ours
  if pgrep -x "$d" >/dev/null && ! pid_of "$BASE/run/$d.pid" "$d" >/dev/null; then
    fail "a $d not started by this check is running: this machine has its own SLURM"
  fi
done
mkdir -p "$BASE"/{etc,state,spool,log,run}
HOST=$(hostname -s)
NODE=$(slurmd -C 2>/dev/null | grep -m1 '^NodeName=') || fail "slurmd -C did not describe this machine"
NCPU=$(sed -n 's/.*CPUs=\([0-9]*\).*/\1/p' <<<"$NODE")
NODE="$NODE NodeAddr=127.0.0.1 State=UNKNOWN"
cat > "$CONF.new" <<EOF
# One-node SLURM for scripts/cluster_check.sh (written by it; do not edit: rewritten on every run).
ClusterName=freezecheck
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation=$BASE/state
SlurmdSpoolDir=$BASE/spool
SlurmctldPidFile=$BASE/run/slurmctld.pid
SlurmdPidFile=$BASE/run/slurmd.pid
SlurmctldLogFile=$BASE/log/slurmctld.log
SlurmdLogFile=$BASE/log/slurmd.log
# no systemd, no cgroup hierarchy to delegate: track processes by parent pid
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
MpiDefault=none
SwitchType=switch/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
# no slurmdbd: sacct has nothing, so job states come from the controller (squeue,
# scontrol), which keeps a finished job for MinJobAge seconds
AccountingStorageType=accounting_storage/none
MinJobAge=600
# every finished job, one line each: the check's proof that jobs went through SLURM
JobCompType=jobcomp/filetxt
JobCompLoc=$BASE/log/jobcomp.txt
$NODE
PartitionName=check Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
if [ -f "$CONF" ] && cmp -s "$CONF" "$CONF.new"; then
  rm -f "$CONF.new"; step "slurm.conf unchanged ($CONF)"
else
  mv "$CONF.new" "$CONF"; step "slurm.conf written ($CONF): node $HOST, $(sed 's/NodeName=[^ ]* //; s/ NodeAddr.*//' <<<"$NODE")"
fi
if [ ! -L "$SYS_CONF" ]; then mkdir -p /etc/slurm; ln -s "$CONF" "$SYS_CONF"; fi
LINKED_CONF=1

# ---------------------------------------------------------------- 3. daemons
if [ ! -s /etc/munge/munge.key ]; then
  mungekey --create --force --keyfile=/etc/munge/munge.key >/dev/null || fail "could not create /etc/munge/munge.key"
  step "munge key created"
fi
chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
mkdir -p /run/munge /var/log/munge /var/lib/munge
chown munge:munge /run/munge /var/log/munge /var/lib/munge
MUNGE_MARK="$BASE/run/munged.started-by-check"
if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
  if [ -f "$MUNGE_MARK" ]; then
    STARTED_MUNGE=1; step "munged already running (left by an earlier check; stopped at the end)"
  else
    step "munged already running (not ours; left running)"
  fi
else
  runuser -u munge -- /usr/sbin/munged || fail "munged did not start (see /var/log/munge/munged.log)"
  STARTED_MUNGE=1
  touch "$MUNGE_MARK"
  munge -n | unmunge >/dev/null 2>&1 || fail "munge does not work after starting munged (see /var/log/munge/munged.log)"
  step "munged started"
fi
left=""
for d in slurmd slurmctld; do
  if pid_of "$BASE/run/$d.pid" "$d" >/dev/null; then left="$left $d"; fi
done
if [ -n "$left" ]; then
  stop_daemons slurmd "$BASE/run/slurmd.pid" slurmctld "$BASE/run/slurmctld.pid"
  step "stopped$left left running by an earlier check"
fi
: > "$BASE/log/jobcomp.txt"
STARTED_SLURM=1
# -c: start from a clean state (no jobs or node states from an earlier check)
slurmctld -c || fail "slurmctld did not start (see $BASE/log/slurmctld.log)"
slurmd || fail "slurmd did not start (see $BASE/log/slurmd.log)"
t=$(date +%s)
state=""
for i in $(seq 1 60); do
  state=$(sinfo -h -N -o '%T' 2>/dev/null | head -1 || true)
  [ "$state" = idle ] && break
  sleep 0.5
done
[ "$state" = idle ] || fail "node not idle after 30 s (state '${state:-no answer}'; see $BASE/log/slurmctld.log and slurmd.log)"
step "slurmctld + slurmd up, node $HOST idle after $(elapsed "$t") s ($(sinfo -h -o '%P %c CPUs %m MB'))"

# ---------------------------------------------------------------- 4. the main job through SLURM
SCRATCH=$(mktemp -d /tmp/freeze-cluster-check.XXXXXX)
export PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1
unset FREEZE_RUN_JSON SNAKEMAKE_PROFILE || true
run_snakemake() {  # run_snakemake DIR ARGS...: snakemake in DIR with DIR/cache as the cache
  local dir="$1"; shift
  mkdir -p "$dir"
  FREEZE_CACHE="$dir/cache" .venv/bin/snakemake -s "$ROOT/Snakefile" --directory "$dir" \
    bop_all --config datasets="$DATASET" "$@" > "$dir/snakemake.log" 2>&1
}
failed_run() {  # failed_run WHAT DIR RC
  tail -n 25 "$2/snakemake.log" | sed 's/^/    | /' >&2
  fail "$1 failed (exit $3); log: $2/snakemake.log"
}

if [ "$EXECUTOR" = slurm ]; then
  PROFILE="$ROOT/profiles/slurm"
  # no accounting here: states from squeue (MinJobAge=600 >= 3 x 2 s, as the plugin requires)
  EXTRA=(--slurm-status-command squeue --slurm-init-seconds-before-status-checks 2
         --slurm-jobname-prefix freezecheck --slurm-keep-successful-logs)
  SUBMITTED_RE='has been submitted with SLURM jobid'
else
  PROFILE="$ROOT/profiles/slurm-generic"
  EXTRA=(--seconds-between-status-checks 3)
  SUBMITTED_RE='with external jobid'
fi
# The local reference runs beside the SLURM run: the SLURM run mostly waits (job starts,
# status polls), so the two together take little more than the SLURM run alone.
LOCAL_PID=""
if [ -z "$REFERENCE" ]; then
  step "running bop_all on $DATASET locally (--cores 2, beside the SLURM run) into $SCRATCH/local"
  T_LOCAL0=$(date +%s)
  ( rc=0; run_snakemake "$SCRATCH/local" --cores 2 || rc=$?; echo "$rc $(elapsed "$T_LOCAL0")" > "$SCRATCH/local.done" ) &
  LOCAL_PID=$!
fi
step "running bop_all on $DATASET through SLURM ($EXECUTOR executor, profile ${PROFILE#"$ROOT"/}) into $SCRATCH/slurm"
t=$(date +%s)
rc=0
run_snakemake "$SCRATCH/slurm" --profile "$PROFILE" --retries 0 --max-threads "$NCPU" "${EXTRA[@]}" || rc=$?
T_SLURM=$(elapsed "$t")
[ "$rc" = 0 ] || failed_run "the SLURM run" "$SCRATCH/slurm" "$rc"
SUBMITTED=$(grep -c "$SUBMITTED_RE" "$SCRATCH/slurm/snakemake.log" || true)
DONE_LINE=$(grep -o '[0-9]* of [0-9]* steps (100%) done' "$SCRATCH/slurm/snakemake.log" | tail -1 || true)
COMPLETED=$(grep -c 'JobState=COMPLETED' "$BASE/log/jobcomp.txt" || true)
NOT_COMPLETED=$(grep -v 'JobState=COMPLETED' "$BASE/log/jobcomp.txt" | grep -c 'JobState=' || true)
step "SLURM run done in $T_SLURM s: $DONE_LINE; $SUBMITTED jobs submitted with sbatch; SLURM's job log: $COMPLETED COMPLETED, $NOT_COMPLETED other"
[ "$SUBMITTED" -gt 0 ] || fail "the SLURM run submitted no job to SLURM (see $SCRATCH/slurm/snakemake.log)"
[ "$COMPLETED" -eq "$SUBMITTED" ] || fail "SLURM recorded $COMPLETED completed jobs for $SUBMITTED submitted (see $BASE/log/jobcomp.txt)"
[ "$NOT_COMPLETED" = 0 ] || fail "SLURM recorded $NOT_COMPLETED jobs that did not complete (see $BASE/log/jobcomp.txt)"

# ---------------------------------------------------------------- 5. the same locally
if [ -n "$REFERENCE" ]; then
  LOCAL_CACHE=$(cd "$REFERENCE" 2>/dev/null && pwd) || fail "--reference $REFERENCE: no such folder"
  step "local reference: $LOCAL_CACHE (not rerun)"
  T_LOCAL=""
else
  wait "$LOCAL_PID" || true
  LOCAL_PID=""
  read -r rc T_LOCAL < "$SCRATCH/local.done" || fail "the local run left no exit status ($SCRATCH/local.done)"
  [ "$rc" = 0 ] || failed_run "the local run" "$SCRATCH/local" "$rc"
  LOCAL_CACHE="$SCRATCH/local/cache"
  step "local run done in $T_LOCAL s"
fi

# ---------------------------------------------------------------- 6. compare
rc=0
CMP=$(.venv/bin/python scripts/slurm/compare_runs.py "$SCRATCH/slurm/cache" "$LOCAL_CACHE" --dataset "$DATASET") || rc=$?
[ "$rc" = 0 ] || fail "SLURM and local results differ: ${CMP#different: }"
step "SLURM vs local: $CMP"
OK=1
step "OK in $(elapsed "$T0") s: $SUBMITTED jobs ran through SLURM ($EXECUTOR executor) in $T_SLURM s${T_LOCAL:+, locally in $T_LOCAL s}; results identical"
exit 0
}
