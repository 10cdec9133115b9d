#!/bin/bash
# visq-server in a cgroup of its own, limited to 3 GiB and half a CPU: its
# budget for work in flight must be half the limit, and its compute workers
# one, as its start-up log says (the readers' cases on files are
# tests/core/resource_limits_test.cpp). Needs a cgroup file system this
# user may write (root, or a delegated v2 subtree); where there is none, it
# says so and is skipped (exit 77).
#   usage: cgroup_limits_test.sh VISQ_SERVER_BINARY
set -u
server=${1:?usage: $0 VISQ_SERVER_BINARY}
skip() { echo "SKIP: $*"; exit 77; }
limit_bytes=$((3 << 30))

made=()
cleanup() {
  [ -n "${server_pid:-}" ] && kill "$server_pid" 2>/dev/null && wait "$server_pid" 2>/dev/null
  for dir in "${made[@]}"; do rmdir "$dir" 2>/dev/null; done
  rm -rf "${scratch:-}"
}
trap cleanup EXIT
scratch=$(mktemp -d)

# A child of the process's own cgroup in each hierarchy, limits written.
if [ -f /sys/fs/cgroup/cgroup.controllers ]; then
  own=$(sed -n 's/^0:://p' /proc/self/cgroup)
  dir=/sys/fs/cgroup${own%/}/visq_limits_test_$$
  mkdir "$dir" 2>/dev/null || skip "cannot make a cgroup under /sys/fs/cgroup$own"
  made+=("$dir")
  { echo "$limit_bytes" > "$dir/memory.max" && echo "50000 100000" > "$dir/cpu.max"; } 2>/dev/null ||
    skip "the memory and cpu controllers are not delegated to /sys/fs/cgroup$own"
  join=("$dir")
else
  memory_own=$(sed -n 's/^[0-9]*:memory://p' /proc/self/cgroup)
  cpu_own=$(sed -n 's/^[0-9]*:\([a-z,]*,\)\{0,1\}cpu\(,[a-z,]*\)\{0,1\}:\(.*\)$/\3/p' /proc/self/cgroup | head -1)
  memory_dir=/sys/fs/cgroup/memory${memory_own%/}/visq_limits_test_$$
  cpu_dir=/sys/fs/cgroup/cpu${cpu_own%/}/visq_limits_test_$$
  mkdir "$memory_dir" 2>/dev/null || skip "cannot make a cgroup v1 memory group"
  made+=("$memory_dir")
  mkdir "$cpu_dir" 2>/dev/null || skip "cannot make a cgroup v1 cpu group"
  made+=("$cpu_dir")
  { echo "$limit_bytes" > "$memory_dir/memory.limit_in_bytes" && echo 100000 > "$cpu_dir/cpu.cfs_period_us" &&
    echo 50000 > "$cpu_dir/cpu.cfs_quota_us"; } 2>/dev/null || skip "cannot write cgroup v1 limits"
  join=("$memory_dir" "$cpu_dir")
fi

# The server joins the groups before it starts (exec keeps the process).
mkdir "$scratch/repo"
bash -c 'for dir in "${@:2}"; do echo $$ > "$dir/cgroup.procs" || exit 3; done; exec "$1" --scene-repo '"$scratch/repo"' --address 127.0.0.1:0' \
  _ "$server" "${join[@]}" > "$scratch/log" 2>&1 &
server_pid=$!
for _ in $(seq 100); do
  grep -q "compute workers" "$scratch/log" && break
  kill -0 "$server_pid" 2>/dev/null || break
  sleep 0.2
done
grep -E "budget for work in flight|compute workers" "$scratch/log"

failed=0
grep -q "budget for work in flight (--max-work-bytes): $((limit_bytes / 2)) bytes, half of cgroup v" "$scratch/log" ||
  { echo "FAIL: the budget is not half of the cgroup's $limit_bytes bytes"; failed=1; }
grep -q "compute workers: 1, from the cgroup v" "$scratch/log" ||
  { echo "FAIL: the compute workers do not follow the quota of half a CPU"; failed=1; }
[ "$failed" = 0 ] || { echo "--- server log:"; cat "$scratch/log"; exit 1; }
echo "PASS: budget $((limit_bytes / 2)) bytes and 1 worker from the cgroup"
