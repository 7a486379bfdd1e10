#!/usr/bin/env bash
# make test-slurm: a two-job `hydra/launcher=slurm` sweep of the smoke experiment, then a
# reduced benchmark (python -m experiments.benchmark) through the same launcher, on a
# private single-node SLURM cluster (Debian's slurm-wlm + munge) started for this test.
#
# Needs root (it installs slurm-wlm and munge with apt-get when missing and starts the
# daemons). Everything it starts lives under one temporary directory: the munge key and
# socket, slurm.conf, the controller's state, spool, pid and log files, and the sweep.
# The daemons are stopped on exit, by the PIDs this script recorded, and the directory
# is removed unless KEEP=1. Ports are picked free at start.
#
#   PY=.venv/bin/python scripts/test_slurm.sh     # PY: the project's Python
#
# A real cluster needs only the launcher overrides (see conf/hydra/launcher/slurm.yaml):
# hydra.launcher.partition=<partition>, and where the site asks for them
# hydra.launcher.account=<account>, hydra.launcher.timeout_min=<min>.
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PY=${PY:-$ROOT/.venv/bin/python}
PARTITION=densityloop
WAIT_S=${WAIT_S:-600}

say() { echo "test-slurm: $*"; }
die() { echo "test-slurm: FAILED: $*" >&2; exit 1; }

if [[ $(id -u) -ne 0 ]]; then
    echo "test-slurm: needs root: it installs slurm-wlm and munge with apt-get and starts" \
        "munged, slurmctld and slurmd (run it as root, e.g. in a disposable VM or container)" >&2
    exit 1
fi
[[ -x $PY ]] || die "no Python at $PY (run make install, or set PY=...)"

missing=()
for cmd in munged slurmctld slurmd sbatch squeue scontrol; do
    command -v "$cmd" >/dev/null 2>&1 || missing+=("$cmd")
done
if ((${#missing[@]})); then
    say "installing slurm-wlm and munge (missing: ${missing[*]})"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq slurm-wlm munge >/dev/null
fi
id munge >/dev/null 2>&1 || die "no user munge after installing munge"

TMP=$(mktemp -d /tmp/densityloop-slurm.XXXXXX)
chmod 755 "$TMP"   # munged, running as user munge, must reach its directory
PIDS=()            # daemons started here, stopped in reverse order on exit

cleanup() {
    local status=$?
    set +e
    if [[ -n ${SLURM_CONF:-} && -f ${SLURM_CONF} ]] && ((${#PIDS[@]} > 1)); then
        scancel --quiet --partition="$PARTITION" 2>/dev/null
    fi
    for ((i = ${#PIDS[@]} - 1; i >= 0; i--)); do
        local pid=${PIDS[i]}
        kill -TERM "$pid" 2>/dev/null || continue
        for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        kill -0 "$pid" 2>/dev/null && kill -KILL "$pid" 2>/dev/null
        wait "$pid" 2>/dev/null
    done
    if ((status != 0)); then
        for log in "$TMP"/log/*.log; do
            [[ -f $log ]] && { echo "--- $log (last lines)"; tail -n 15 "$log"; }
        done
    fi
    if [[ ${KEEP:-0} == 1 ]]; then say "kept $TMP"; else rm -rf "$TMP"; fi
    exit "$status"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

free_port() {
    "$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# --- munge: a fresh key and a private socket --------------------------------------------
# the key in a private directory, the socket in one every user can reach
mkdir -p "$TMP/munge" "$TMP/munge-run" "$TMP/log" "$TMP/state" "$TMP/spool"
dd if=/dev/urandom of="$TMP/munge/munge.key" bs=1024 count=1 status=none
chown -R munge:munge "$TMP/munge" "$TMP/munge-run"
chmod 700 "$TMP/munge"
chmod 755 "$TMP/munge-run"
chmod 400 "$TMP/munge/munge.key"
SOCKET=$TMP/munge-run/munge.socket
setpriv --reuid=munge --regid=munge --init-groups \
    munged --foreground --socket="$SOCKET" --key-file="$TMP/munge/munge.key" \
    --pid-file="$TMP/munge-run/munged.pid" --seed-file="$TMP/munge/munged.seed" \
    --log-file="$TMP/log/munged.log" >"$TMP/log/munged.out" 2>&1 &
PIDS+=($!)
for _ in $(seq 50); do [[ -S $SOCKET ]] && break; sleep 0.1; done
[[ -S $SOCKET ]] || die "munged did not start"
munge --socket="$SOCKET" -n | unmunge --socket="$SOCKET" >/dev/null || die "munge round trip failed"
say "munged up (pid ${PIDS[-1]})"

# --- slurm.conf: controller and node on 127.0.0.1, one partition ------------------------
HOST=$(hostname -s)
CPUS=$(nproc)
MEM_MB=$(slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p')
[[ -n $MEM_MB ]] || MEM_MB=$(($(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024))
export SLURM_CONF=$TMP/slurm.conf
cat >"$SLURM_CONF" <<EOF
ClusterName=densityloop-test
SlurmctldHost=$HOST(127.0.0.1)
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$SOCKET
StateSaveLocation=$TMP/state
SlurmdSpoolDir=$TMP/spool/%n
SlurmctldPidFile=$TMP/slurmctld.pid
SlurmdPidFile=$TMP/slurmd.pid
SlurmctldLogFile=$TMP/log/slurmctld.log
SlurmdLogFile=$TMP/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=$PARTITION Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF

slurmctld -D -f "$SLURM_CONF" >"$TMP/log/slurmctld.out" 2>&1 &
PIDS+=($!)
slurmd -D -f "$SLURM_CONF" >"$TMP/log/slurmd.out" 2>&1 &
PIDS+=($!)
say "slurmctld (pid ${PIDS[1]}) and slurmd (pid ${PIDS[2]}) started; config $SLURM_CONF"
state=""
for _ in $(seq 60); do
    state=$(sinfo --noheader --partition="$PARTITION" --format=%T 2>/dev/null | head -n1 || true)
    [[ $state == idle ]] && break
    sleep 1
done
[[ $state == idle ]] || die "node not idle after 60 s (state '${state:-none}')"
say "node $HOST idle: $CPUS CPUs, $MEM_MB MB, partition $PARTITION"

# --- the sweep ------------------------------------------------------------------------
SWEEP=$TMP/sweep
cd "$ROOT"
say "sweep: seed=1,2 through hydra/launcher=slurm into $SWEEP"
timeout "$WAIT_S" "$PY" -m experiments.closed_loop -m +experiment=smoke seed=1,2 \
    hydra/launcher=slurm hydra.launcher.partition="$PARTITION" \
    hydra.launcher.timeout_min=10 hydra.launcher.mem_gb=1 \
    hydra.sweep.dir="$SWEEP" log.progress=off ||
    die "the sweep exited with status $?"

# --- checks: both logs complete, the status table says so --------------------------------
"$PY" - "$SWEEP" <<'EOF'
import csv
import sys
from pathlib import Path

from analysis.load import load_run

sweep = Path(sys.argv[1])
logs = sorted(sweep.glob("*/run.mcap"))
assert len(logs) == 2, f"expected 2 logs, found {[str(p) for p in logs]}"
for path in logs:
    log = load_run(path)
    assert log.state == "completed", f"{path}: state {log.state}"
    assert log.recovery is None, f"{path}: {log.recovery}"
    seed = log.metadata["provenance"]["seed"]
    print(f"test-slurm: {path.parent.name}: completed, seed {seed}, "
          f"{len(log.metrics['t'])} metric rows, t_end = {log.metrics['t'][-1]:.2f} s")
rows = list(csv.DictReader(open(sweep / "sweep_status.csv")))
assert len(rows) == 2, f"sweep_status.csv has {len(rows)} rows"
assert all(r["state"] == "completed" for r in rows), rows
seeds = sorted(o for r in rows for o in r["overrides"].split() if o.startswith("seed="))
assert seeds == ["seed=1", "seed=2"], rows
print("test-slurm: sweep_status.csv: " + "; ".join(f"{r['overrides']}: {r['state']}" for r in rows))
EOF
# the controller's own record: both array tasks ran there and completed
DONE=$(scontrol --oneliner show job | grep -c 'JobState=COMPLETED' || true)
((DONE == 2)) || die "slurmctld reports $DONE completed jobs, expected 2"
say "slurmctld: $DONE jobs COMPLETED on $HOST"

# --- a reduced benchmark through the same launcher ------------------------------------------
BENCH=$TMP/benchmark
cat >"$TMP/tier.yaml" <<'TIER'
scenarios: [paper]
laws: [paper, langevin]
trials: 2
tuning_seeds: [0]
verdict_seeds: [5, 6]
budget_law: paper
values:
  grid: {n: 12}
  agents: {n: 64}
  sim: {t_final: 0.5}
  log: {field_every: 1000, positions_every: 5, w2_every: 1000, floor_draws: 2}
TIER
say "benchmark: a reduced tier through hydra/launcher=slurm into $BENCH"
timeout "$WAIT_S" "$PY" -m experiments.benchmark --tier "$TMP/tier.yaml" --out "$BENCH" \
    --page "$BENCH/page/benchmark.md" --launcher hydra/launcher=slurm \
    --launcher hydra.launcher.partition="$PARTITION" --launcher hydra.launcher.timeout_min=10 \
    --launcher hydra.launcher.mem_gb=1 ||
    die "the benchmark exited with status $?"
"$PY" - "$BENCH" <<'CHECK'
import json
import sys
from pathlib import Path

bench = Path(sys.argv[1])
verdicts = sorted(bench.glob("verdict/*/run.mcap"))
assert verdicts, "no verdict logs"
data = json.loads((bench / "page" / "benchmark" / "data.json").read_text())
(scenario,) = data["scenarios"]
for entry in scenario["laws"]:
    roles = entry["roles"]
    assert "default" in roles and roles["default"]["completed"] == 2, entry
print(f"test-slurm: benchmark: {len(verdicts)} verdict runs; leaderboard {bench / 'page'}")
CHECK
DONE=$(scontrol --oneliner show job | grep -c 'JobState=COMPLETED' || true)
((DONE > 2)) || die "slurmctld reports $DONE completed jobs after the benchmark"
say "slurmctld: $DONE jobs COMPLETED on $HOST in all"
say "PASSED"
