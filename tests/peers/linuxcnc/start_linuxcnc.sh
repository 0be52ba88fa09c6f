#!/usr/bin/env bash
# Start LinuxCNC 2.9 (Debian linuxcnc-uspace) headless, as root or not, on 127.0.0.1:PORT with
# linuxcncrsh as its "display", using the packaged 5-axis table-rotary-tilting sample with its
# GUI parts (vismach, pyvcp, ngcgui, hal_manualtoolchange) removed.
#
#   start_linuxcnc.sh [--kins xyzbc|xyzac] [--port N] [--dir DIR] [--probe-comp FILE.py]
#                     [--halcmd "HAL COMMAND"]... [--timeout S]
#       Starts it in the background and prints shell-style lines on stdout:
#         LCNC_DIR=… LCNC_PORT=… LCNC_PID=… LCNC_INI=… LCNC_LOG=…
#       Exit 0 once linuxcncrsh accepts connections, non-zero (log tail on stderr) otherwise.
#   start_linuxcnc.sh --stop DIR
#       Stops the instance started with that DIR (SIGTERM to its linuxcncrsh, after which the
#       linuxcnc script runs its own cleanup, ~2 s; then TERM/KILL to whatever of this instance
#       is left, by PID) and removes DIR if this script created it. `shutdown` sent over
#       linuxcncrsh ends it too; --stop is still needed then to remove the folders.
#
# --probe-comp FILE.py: a userspace HAL component (Python, `import hal`) loaded with
#   `loadusr -Wn rumba-probe /usr/bin/python3 FILE.py` whose bit pin `rumba-probe.out`
#   is netted to motion.probe-input. The component must call hal.component("rumba-probe").
# --halcmd "…": an extra [HAL]HALCMD line (repeatable), e.g.
#   --halcmd "net probe-z joint.2.pos-fb => rumba-probe.z"
#
# See ../PEERS_FINDINGS.md for the protocol, pitfalls and the kinematics formulas.
set -euo pipefail

SAMPLE_SUBDIR=sim/axis/vismach/5axis/table-rotary-tilting
SAMPLE_ROOTS=(
  /usr/share/doc/linuxcnc/examples/sample-configs
  /usr/share/linuxcnc/examples/sample-configs
  /usr/share/doc/linuxcnc-uspace/examples/sample-configs
)

die() { echo "start_linuxcnc.sh: $*" >&2; exit 2; }

free_port() {
  /usr/bin/python3 - <<'EOF'
import socket
s = socket.socket()
s.bind(("127.0.0.1", 0))
print(s.getsockname()[1])
s.close()
EOF
}

lcnc_running() {  # a live (not zombie) LinuxCNC daemon anywhere on the machine?
  ps -C milltask,linuxcncsvr,rtapi_app -o stat= 2>/dev/null | grep -qv '^Z'
}

alive() {  # process exists and is not a zombie
  local st
  st=$(awk '{print $3}' "/proc/$1/stat" 2>/dev/null) && [[ -n $st && $st != Z ]]
}

stop_instance() {
  local dir=$1 pid pgid i fifo
  fifo=$(cat "$dir/fifo.path" 2>/dev/null || echo "$dir/fifo")
  [[ -f $dir/linuxcnc.pid ]] || die "no $dir/linuxcnc.pid"
  pid=$(cat "$dir/linuxcnc.pid")
  pgid=$(cat "$dir/linuxcnc.pgid" 2>/dev/null || echo "$pid")
  if alive "$pid"; then
    # The linuxcnc script runs its display (linuxcncrsh) in the foreground and defers its TERM
    # trap until that returns: end linuxcncrsh, and the script runs its own Cleanup (~2 s).
    local rsh
    rsh=$( (ps -o pid= -o comm= --ppid "$pid" || true) | awk '$2 == "linuxcncrsh" {print $1}')
    if [[ -n $rsh ]]; then kill -TERM $rsh 2>/dev/null || true; else kill -TERM "$pid" || true; fi
    for i in $(seq 150); do alive "$pid" || break; sleep 0.1; done
  fi
  # anything left: the process group (milltask, io, halui, linuxcncrsh, loadusr components) and
  # the daemons that detach into their own sessions (rtapi_app, linuxcncsvr), found by the
  # RTAPI_FIFO_PATH of this instance in their environment.
  # Never this script or its callers, which may have exported the same RTAPI_FIFO_PATH (halcmd).
  local left=() p mine=" " q=$$
  while [[ $q =~ ^[0-9]+$ ]] && ((q > 1)); do
    mine+="$q "
    q=$(awk '{print $4}' "/proc/$q/stat" 2>/dev/null || echo 1)
  done
  for p in /proc/[0-9]*; do
    [[ $mine == *" ${p#/proc/} "* || ${p#/proc/} == "$BASHPID" ]] && continue
    if grep -qsz "^RTAPI_FIFO_PATH=$fifo/" "$p/environ" 2>/dev/null; then left+=("${p#/proc/}"); fi
  done
  if kill -0 -- "-$pgid" 2>/dev/null || ((${#left[@]})); then
    kill -TERM -- "-$pgid" 2>/dev/null || true
    ((${#left[@]})) && kill -TERM "${left[@]}" 2>/dev/null || true
    sleep 1
    kill -KILL -- "-$pgid" 2>/dev/null || true
    ((${#left[@]})) && kill -KILL "${left[@]}" 2>/dev/null || true
    for i in $(seq 20); do lcnc_running || break; sleep 0.1; done
  fi
  # A hard kill skips the script's own Cleanup: if no LinuxCNC is left, drop its lock and its
  # shared memory (NML keys 1001-1005, RTAPI/HAL keys 100, 'HAL2', 'HHL4'); stale segments make
  # the next instance hang.
  if ! lcnc_running; then
    rm -f /tmp/linuxcnc.lock
    local key
    for key in 0x000003e9 0x000003ea 0x000003eb 0x000003ec 0x000003ed 0x00000064 0x48414c32 \
      0x48484c34; do
      ipcs -m | awk -v k="$key" '$1 == k && $6 == 0 {print $2}' | xargs -r -n1 ipcrm -m
    done
  fi
  if [[ $fifo == /tmp/rumba-rtapi.* ]]; then rm -rf -- "$fifo"; fi
  if [[ -f $dir/.created-by-start-linuxcnc ]]; then rm -rf -- "$dir"; fi
}

KINS=xyzbc PORT="" DIR="" PROBE_COMP="" TIMEOUT=60 HALCMDS=()
while (($#)); do
  case $1 in
    --kins) KINS=$2; shift 2 ;;
    --port) PORT=$2; shift 2 ;;
    --dir) DIR=$2; shift 2 ;;
    --probe-comp) PROBE_COMP=$(readlink -f "$2"); shift 2 ;;
    --timeout) TIMEOUT=$2; shift 2 ;;
    --halcmd) HALCMDS+=("$2"); shift 2 ;;
    --stop) stop_instance "$2"; exit 0 ;;
    -h|--help) sed -n '2,24p' "$0"; exit 0 ;;
    *) die "unknown argument: $1" ;;
  esac
done
[[ $KINS == xyzbc || $KINS == xyzac ]] || die "--kins must be xyzbc or xyzac"
command -v linuxcnc >/dev/null || die "linuxcnc not installed (bash .ci/install-peers.sh linuxcnc)"

SAMPLE=""
for r in "${SAMPLE_ROOTS[@]}"; do
  if [[ -f $r/$SAMPLE_SUBDIR/$KINS-trt.ini ]]; then SAMPLE=$r/$SAMPLE_SUBDIR; break; fi
done
[[ -n $SAMPLE ]] || die "sample config $SAMPLE_SUBDIR/$KINS-trt.ini not found"

# One LinuxCNC per machine: the linuxcnc script keeps /tmp/linuxcnc.lock, and a second start
# without a tty "cleans up the other instance" (kills every milltask/linuxcncrsh by name).
if [[ -e /tmp/linuxcnc.lock ]] && lcnc_running; then
  die "another LinuxCNC is running (/tmp/linuxcnc.lock); only one instance per machine"
fi

if [[ -z $DIR ]]; then
  DIR=$(mktemp -d "${TMPDIR:-/tmp}/rumba-lcnc.XXXXXX")
  touch "$DIR/.created-by-start-linuxcnc"
fi
mkdir -p "$DIR"
DIR=$(readlink -f "$DIR")
[[ -n $PORT ]] || PORT=$(free_port)

mkdir -p "$DIR/home" "$DIR/nc_files"
# As root, rtapi_app drops to RTAPI_UID (65534) and binds its fifo socket there: the folder must
# be writable by that uid and every parent traversable, which a mktemp -d (0700) folder is not.
# So the fifo folder is its own 1777 folder directly under /tmp.
FIFO_DIR=$(mktemp -d /tmp/rumba-rtapi.XXXXXX)
chmod 1777 "$FIFO_DIR"
echo "$FIFO_DIR" >"$DIR/fifo.path"
rm -rf "$DIR/config"
cp -r "$SAMPLE" "$DIR/config"
chmod -R u+w "$DIR/config"
INI=$DIR/config/$KINS-trt.ini

# Rewrite the INI: no GUI, linuxcncrsh on PORT, no pyvcp/ngcgui/vismach, no manual tool change.
/usr/bin/python3 - "$INI" "$PORT" "$KINS" "$DIR/nc_files" "$PROBE_COMP" "${HALCMDS[@]}" <<'EOF'
import re, sys
ini, port, kins, ncdir, probe = sys.argv[1:6]
extra = sys.argv[6:]
added = []
if probe:
    added.append(f"HALCMD = loadusr -Wn rumba-probe /usr/bin/python3 {probe}\n")
    added.append("HALCMD = net rumba-probe-trip rumba-probe.out => motion.probe-input\n")
added += [f"HALCMD = {c}\n" for c in extra]
out, section = [], None
for line in [*open(ini), None]:
    s = line.strip() if line is not None else "[END]"
    m = re.match(r"\[(\w+)\]", s)
    if m:
        if section == "HAL":  # extra HAL commands go last in [HAL]
            out.extend(["# added by start_linuxcnc.sh\n", *added, "\n"])
        section = m.group(1)
        if line is not None:
            out.append(line)
        continue
    key = s.split("=", 1)[0].strip() if "=" in s and not s.startswith("#") else None
    if section == "DISPLAY":
        if key == "DISPLAY":
            line = f"DISPLAY = linuxcncrsh --port {port}\n"
        elif key in {"PYVCP", "TKPKG", "NGCGUI_FONT", "NGCGUI_SUBFILE", "INTRO_GRAPHIC",
                     "INTRO_TIME", "OPEN_FILE", "EDITOR", "TOOL_EDITOR"}:
            line = "#" + line
        elif key == "PROGRAM_PREFIX":
            line = f"PROGRAM_PREFIX = {ncdir}\n"
    elif section == "HAL":
        if key == "HALFILE" and "basic_sim.tcl" in s:
            line = "HALFILE = LIB:basic_sim.tcl -no_use_hal_manualtoolchange\n"
        elif key == "POSTGUI_HALFILE":
            line = "#" + line
        elif key == "HALCMD" and f"{kins}-trt-gui" in s:
            if "loadusr" in s:
                line = "#" + line
            elif re.search(r"\bjoint\.\d+\.pos-fb\b", s):
                line = "#" + line  # vismach feeders only: leave joint.N.pos-fb free
            else:  # keep the kins pins, drop the vismach ones
                line = re.sub(rf"\s+{kins}-trt-gui\.\S+", "", line)
    elif section == "APPLICATIONS" and key == "APP":
        line = "#" + line
    out.append(line)
open(ini, "w").writelines(out)
EOF

LOG=$DIR/linuxcnc.log
(
  cd "$DIR/config"
  unset DISPLAY WAYLAND_DISPLAY XAUTHORITY
  export HOME=$DIR/home RTAPI_FIFO_PATH=$FIFO_DIR/rtapi_fifo
  [[ $(id -u) == 0 ]] && export RTAPI_UID=65534
  # /usr/bin first: LinuxCNC's python modules are built for Debian's python3 only.
  export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH
  # -r: keep stdout/stderr (without a tty linuxcnc sends them to /tmp/linuxcnc.*.XXXXXX files
  #     that it deletes at exit). setsid: own session and process group (pgid == pid of the
  #     linuxcnc script), so --stop can find all of it.
  exec setsid /bin/bash -c 'echo $$ >"$1/linuxcnc.pid"; echo $$ >"$1/linuxcnc.pgid"; shift; exec "$@"' \
    _ "$DIR" linuxcnc -r "$INI" </dev/null >"$LOG" 2>&1
) &
for _ in $(seq 50); do [[ -s $DIR/linuxcnc.pid ]] && break; sleep 0.1; done
PID=$(cat "$DIR/linuxcnc.pid")

deadline=$((SECONDS + TIMEOUT))
until /usr/bin/python3 -c "import socket,sys; socket.create_connection(('127.0.0.1',$PORT),0.5).close()" 2>/dev/null; do
  if ! kill -0 "$PID" 2>/dev/null || ((SECONDS >= deadline)); then
    echo "start_linuxcnc.sh: linuxcncrsh did not come up on 127.0.0.1:$PORT; log tail:" >&2
    grep -v 'Running with fallback_uid' "$LOG" | tail -n 40 >&2 || true
    stop_instance "$DIR" || true
    exit 1
  fi
  sleep 0.2
done
echo "LCNC_DIR=$DIR"
echo "LCNC_PORT=$PORT"
echo "LCNC_PID=$PID"
echo "LCNC_INI=$INI"
echo "LCNC_LOG=$LOG"
