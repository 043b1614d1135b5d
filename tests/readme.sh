#!/usr/bin/env bash
# Runs the README's commands as written, so that they cannot drift from what the code does:
# every ```sh block of README.md, extracted here (nothing is copied by hand). The block with
# `cargo run --release -- serve` is started first, in the background, and must answer /healthz;
# then the blocks that build and use the command line (`B=...`), then the rest (curl, the
# client) against that server. A command passes when it exits 0 and every file it names with
# `-o` exists and is not empty, and it printed no line starting with `error:` on stderr (a
# harmless message from a library, Vulkan's loader say, reads as ours: a command that
# succeeded must not print one).
#
# Adjustments, all on the outside of the commands: the server listens on a free port (through
# FRACTILE_BIND, the environment variable the README documents) and `localhost:8080` in the
# commands is pointed at it; the client finds it through FRACTILE_SERVER; curl runs with a
# curlrc that adds --fail; the demo cache is a fresh folder. NODEVICE_SELECT, which CI sets
# for the test suite, is unset here: a user's shell has none. Lines left out, each said aloud:
# `cargo test` (this script is part of that run's CI), and `--backend gpu` lines unless a
# hardware GPU is at hand (README_GPU=1). Files the commands write at the top of the repository
# are removed at the end. Prints a closing "N passed, N failed" line.
set -uo pipefail
cd "$(dirname "$0")/.."
unset NODEVICE_SELECT
ROOT=$(pwd)
PORT=${PORT:-18211}
# A port nothing listens on (a server left by another run must not answer for ours).
while (exec 3<>"/dev/tcp/127.0.0.1/$PORT") 2>/dev/null; do PORT=$((PORT + 1)); done
WORK=$(mktemp -d)
before=$(ls -A)

cleanup() {
  # The server runs in a process group of its own (cargo and the server it starts): end both.
  [ -n "${SERVER_PID:-}" ] && kill -- "-$SERVER_PID" 2>/dev/null && wait "$SERVER_PID" 2>/dev/null
  # What the commands wrote at the top of the repository.
  for f in $(ls -A); do
    grep -qxF "$f" <<<"$before" || rm -rf -- "$f"
  done
  rm -rf "$WORK"
}
trap cleanup EXIT

# Every ```sh block, continuation lines joined, one command a line, tagged with its block.
awk -v q='```' '
  $0 == q "sh" { inb = 1; n++; next }
  inb && $0 == q { inb = 0; next }
  inb {
    line = $0
    if (cont != "") { line = cont " " line; cont = "" }
    if (line ~ /\\$/) { sub(/\\$/, "", line); cont = line; next }
    print n "\t" line
  }' README.md >"$WORK/commands"

serve_block=$(awk -F'\t' '$2 ~ /cargo run --release -- serve/ { print $1; exit }' "$WORK/commands")
[ -n "$serve_block" ] || { echo "README has no 'cargo run --release -- serve' block"; echo "0 passed, 1 failed"; exit 1; }
serve_cmd=$(awk -F'\t' -v b="$serve_block" '$1 == b && $2 ~ /serve/ { print $2; exit }' "$WORK/commands")

pass=0; fail=0; skip=0
ok() { pass=$((pass + 1)); echo "ok: $1"; }
bad() { fail=$((fail + 1)); echo "FAILED: $1"; }

echo "starting the README's server: $serve_cmd"
export FRACTILE_BIND=127.0.0.1:$PORT FRACTILE_CACHE=$WORK/cache FRACTILE_BACKEND=cpu RUST_LOG=warn
setsid bash -c "exec $serve_cmd" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
up=0
# The command compiles the server package first when it is not built yet (minutes).
for _ in $(seq 1 900); do
  if curl -fs "http://127.0.0.1:$PORT/healthz" >/dev/null 2>&1; then up=1; break; fi
  kill -0 "$SERVER_PID" 2>/dev/null || break
  sleep 1
done
if [ $up = 1 ]; then ok "$serve_cmd answers /healthz"; else
  bad "$serve_cmd answers /healthz"; tail -20 "$WORK/server.log"
  echo "$pass passed, $fail failed"; exit 1
fi

export FRACTILE_SERVER=http://127.0.0.1:$PORT
# Errors as a user sees them (anyhow prints a backtrace under RUST_BACKTRACE=1).
export RUST_BACKTRACE=0
export CURL_HOME=$WORK
printf 'fail\nsilent\nshow-error\nmax-time = 300\n' >"$WORK/.curlrc"
# Input the client's points example reads (lon,lat rows on the jacksboro DEM, one outside).
printf -- '-84.2,36.6\n-84.25,36.55\n-80,30\n' >points.csv

# Blocks with the command line first (they make the .fra files later blocks use), then the rest.
cli_blocks=$(awk -F'\t' '$2 ~ /^B=/ { print $1 }' "$WORK/commands" | sort -un)
order=$( (echo "$cli_blocks"; awk -F'\t' '{ print $1 }' "$WORK/commands" | sort -un) | awk 'NF && !seen[$0]++')

run() {
  local line=$1 cmd
  cmd=${line//localhost:8080/127.0.0.1:$PORT}
  case "$line" in
    *"cargo test"*) skip=$((skip + 1)); echo "skipped (the test suite itself): $line"; return ;;
    *"-- serve"*) return ;;
    *"--backend gpu"*)
      if [ "${README_GPU:-0}" != 1 ]; then skip=$((skip + 1)); echo "skipped (needs a hardware GPU; README_GPU=1 runs it): $line"; return; fi ;;
  esac
  # Assignments (B=..., C=...) set the variables the next lines use.
  if [[ "$cmd" =~ ^[A-Z_]+=[^[:space:]]+[[:space:]]*(#.*)?$ ]]; then eval "$cmd"; return; fi
  local outs
  outs=$(grep -oE '(^| )(-o|--output) [^ ]+' <<<"${cmd%%#*}" | awk '{ print $2 }')
  for o in $outs; do rm -rf -- "$(eval echo "$o")"; done
  if (eval "$cmd") </dev/null >"$WORK/out" 2>"$WORK/err"; then
    if grep -q '^error:' "$WORK/err"; then
      bad "$line (succeeded, but printed an error: line)"; grep '^error:' "$WORK/err" | head -5; return
    fi
    for o in $outs; do
      o=$(eval echo "$o")
      if [ -d "$o" ] && [ -n "$(ls -A "$o")" ] || [ -s "$o" ]; then :; else
        bad "$line (wrote no $o)"; return
      fi
    done
    ok "$line"
  else
    bad "$line"; head -c 2000 "$WORK/out"; head -c 2000 "$WORK/err"
  fi
}

for b in $order; do
  [ "$b" = "$serve_block" ] && continue
  while IFS=$'\t' read -r blk line; do
    [ "$blk" = "$b" ] && run "$line"
  done <"$WORK/commands"
done
# The server must have lived through all of it.
if kill -0 "$SERVER_PID" 2>/dev/null; then ok "the server is still up"; else
  bad "the server is still up"; echo "its log ends:"; tail -30 "$WORK/server.log"
fi
echo "$pass passed, $fail failed, $skip skipped"
[ "$fail" = 0 ]
