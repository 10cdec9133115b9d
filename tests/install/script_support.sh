# Sourced by the install tests' scripts once they have set `scratch`: on
# exit the server they started (server_pid) is stopped and the scratch folder
# removed; `fail` says what failed with the server log's tail; `step` prints
# a line with the seconds since the script started.
server_pid=""
cleanup() {
  if [[ -n "$server_pid" ]]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
  rm -rf "$scratch"
}
trap cleanup EXIT
fail() {
  echo "FAILED: $*"
  [[ -f "$scratch/server.log" ]] && { echo "--- visq-server log"; tail -n 40 "$scratch/server.log"; }
  exit 1
}
step() { printf '[%3d s] %s\n' "$SECONDS" "$*"; }
# Waits up to 60 s for the server started as server_pid to write its bound
# port into $scratch/port, and sets `port`.
wait_for_port() {
  port=""
  for _ in $(seq 600); do
    port=$(cat "$scratch/port" 2>/dev/null || true)
    [[ -n "$port" && "$port" != 0 ]] && return 0
    kill -0 "$server_pid" 2>/dev/null || fail "visq-server exited during start-up"
    sleep 0.1
  done
  fail "visq-server wrote no port in 60 s"
}
