#!/usr/bin/env bash
# Install the independent peers the tests talk to (see tests/peers/PEERS_FINDINGS.md).
#
#   bash .ci/install-peers.sh [PEER...]       PEER: socat mbpoll node-opcua chromium linuxcnc
#                                             postgresql mosquitto aqdefreader
#                                             (default: all of them)
#
# Idempotent: what is installed already is skipped (a second run with everything present takes
# well under a second); `apt-get update` runs once, and only when a Debian package is missing.
# Debian packages come from Debian's own bookworm repositories, without recommends (linuxcnc-uspace
# would otherwise pull an RT kernel, Qt and OpenCV). node-opcua goes to .peers/node/ (git-ignored;
# RUMBA_PEERS_DIR=DIR puts it in DIR/node instead). aqdefreader (an independent Q-DAS reader)
# goes to its own venv in .peers/aqdef/: it needs pandas, which the product does not.
# Prints one timing line per peer and a version summary at the end.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

# 2.183+ declare engines node>=22.13; the machine's Node is 20 (Debian's would be 18).
NODE_OPCUA_VERSION=2.182.2
# The official OPC UA companion nodesets (DI, IA, Machinery, Machinery Result …) as XML: the
# daemon's OPC UA results server loads them (opcua_server.nodesets_dir) and the node-opcua
# peer checks the server against them. 2.182.0 is the version node-opcua 2.182.2 depends on.
NODE_OPCUA_NODESETS_VERSION=2.182.0
NODE_PREFIX=${RUMBA_PEERS_DIR:-.peers}/node
# pandas 3 breaks the reader's own create_column_dataframe (tests/peers/PEERS_FINDINGS.md); the
# reading the tests use works on both, pinned below 3 all the same.
AQDEF_VERSION=1.3.0
AQDEF_PREFIX=${RUMBA_PEERS_DIR:-.peers}/aqdef
PYTHON=${PYTHON:-python3.11}

ALL_PEERS=(socat mbpoll node-opcua chromium linuxcnc postgresql mosquitto aqdefreader)
declare -A APT_PKGS=(
  [socat]="socat"
  [mbpoll]="mbpoll libmodbus-dev pkg-config"
  [chromium]="chromium chromium-driver poppler-utils"  # poppler: pdftoppm renders report PDFs
  [postgresql]="postgresql"  # the tests start their own server (initdb + pg_ctl) in a temp dir
  [mosquitto]="mosquitto"  # the tests start their own broker on a free loopback port
  # -dev: halcompile and the kinematics headers, to build config/linuxcnc/xyzbc_head_kins.comp
  # (the swivel-head kins module whose pins hold what probing sees); the same
  # version as linuxcnc-uspace (both from bookworm)
  [linuxcnc]="linuxcnc-uspace linuxcnc-uspace-dev"
)

log() { printf 'install-peers: %s\n' "$*"; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1fs", b - a }'; }

SUDO=()
if [[ $(id -u) != 0 ]]; then
  command -v sudo >/dev/null || { log "not root and no sudo: cannot apt-get install"; exit 1; }
  SUDO=(sudo)
fi
export DEBIAN_FRONTEND=noninteractive

peers=("$@")
((${#peers[@]})) || peers=("${ALL_PEERS[@]}")
for p in "${peers[@]}"; do
  case " ${ALL_PEERS[*]} " in
    *" $p "*) ;;
    *) log "unknown peer '$p' (known: ${ALL_PEERS[*]})"; exit 2 ;;
  esac
done

deb_installed() {  # all given Debian packages installed?
  local pkg
  for pkg in "$@"; do
    [[ $(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null) == "install ok installed" ]] || return 1
  done
}

APT_UPDATED=0
apt_install() {  # apt_install PKG... (apt-get update first, once per run)
  if ((APT_UPDATED == 0)); then
    local t0
    t0=$(now)
    "${SUDO[@]}" apt-get update -q -o DPkg::Lock::Timeout=300 >/dev/null
    APT_UPDATED=1
    log "apt-get update: $(since "$t0")"
  fi
  "${SUDO[@]}" apt-get install -y -q --no-install-recommends -o DPkg::Lock::Timeout=300 "$@" \
    >/dev/null
}

node_opcua_version() {  # node_opcua_version [PACKAGE]: installed version of node-opcua (or PACKAGE)
  local pj=$NODE_PREFIX/node_modules/${1:-node-opcua}/package.json
  [[ -f $pj ]] && node -p "require(process.argv[1]).version" "$(readlink -f "$pj")" 2>/dev/null || true
}

aqdef_version() {  # the installed aqdefreader's version, or nothing
  [[ -x $AQDEF_PREFIX/bin/python ]] &&
    "$AQDEF_PREFIX/bin/python" -c 'import importlib.metadata as m; print(m.version("aqdefreader"))' \
      2>/dev/null || true
}

install_peer() {
  local peer=$1 t0 pkgs
  t0=$(now)
  if [[ $peer == aqdefreader ]]; then
    if [[ $(aqdef_version) == "$AQDEF_VERSION" ]]; then
      log "aqdefreader: already installed ($AQDEF_VERSION in $AQDEF_PREFIX) $(since "$t0")"
      return
    fi
    "$PYTHON" -m venv "$AQDEF_PREFIX"
    "$AQDEF_PREFIX/bin/python" -m pip install --quiet "aqdefreader==$AQDEF_VERSION" 'pandas<3' \
      chardet >/dev/null
    [[ $(aqdef_version) == "$AQDEF_VERSION" ]] || { log "aqdefreader: install failed"; exit 1; }
    log "aqdefreader: installed $AQDEF_VERSION into $AQDEF_PREFIX in $(since "$t0")"
    return
  fi
  if [[ $peer == node-opcua ]]; then
    if [[ $(node_opcua_version) == "$NODE_OPCUA_VERSION" &&
          $(node_opcua_version node-opcua-nodesets) == "$NODE_OPCUA_NODESETS_VERSION" ]]; then
      log "node-opcua: already installed ($NODE_OPCUA_VERSION in $NODE_PREFIX) $(since "$t0")"
      return
    fi
    if ! command -v npm >/dev/null || ! command -v node >/dev/null; then
      apt_install nodejs npm
    fi
    mkdir -p "$NODE_PREFIX"
    npm install --prefix "$NODE_PREFIX" --no-audit --no-fund --save-exact --engine-strict \
      --loglevel=error "node-opcua@$NODE_OPCUA_VERSION" \
      "node-opcua-nodesets@$NODE_OPCUA_NODESETS_VERSION" >/dev/null
    [[ $(node_opcua_version) == "$NODE_OPCUA_VERSION" ]] || { log "node-opcua: install failed"; exit 1; }
    [[ $(node_opcua_version node-opcua-nodesets) == "$NODE_OPCUA_NODESETS_VERSION" ]] ||
      { log "node-opcua-nodesets: install failed"; exit 1; }
    log "node-opcua: installed $NODE_OPCUA_VERSION into $NODE_PREFIX in $(since "$t0")"
    return
  fi
  read -r -a pkgs <<<"${APT_PKGS[$peer]}"
  if deb_installed "${pkgs[@]}"; then
    log "$peer: already installed (${pkgs[*]}) $(since "$t0")"
    return
  fi
  apt_install "${pkgs[@]}"
  deb_installed "${pkgs[@]}" || { log "$peer: install of ${pkgs[*]} failed"; exit 1; }
  log "$peer: installed ${pkgs[*]} in $(since "$t0")"
}

T_ALL=$(now)
for p in "${peers[@]}"; do install_peer "$p"; done

# Versions (each command answers in well under a second). Under pipefail a reader that quits
# early (head, awk's exit) kills the writer with SIGPIPE and the whole script with 141, so
# every reader here consumes its input to the end.
first_line() { awk 'NR == 1'; }

for p in "${peers[@]}"; do
  case $p in
    socat) v=$(socat -V | awk '/socat version/ && !v {v = $3} END {print v}') ;;
    mbpoll) v="mbpoll $(dpkg-query -W -f='${Version}' mbpoll), libmodbus $(pkg-config --modversion libmodbus)" ;;
    node-opcua) v="node-opcua $(node_opcua_version), node-opcua-nodesets $(node_opcua_version node-opcua-nodesets) on node $(node --version)" ;;
    chromium) v="$(chromium --version 2>/dev/null | first_line); $(chromedriver --version | cut -d' ' -f1-2); $(pdftoppm -v 2>&1 | first_line)" ;;
    linuxcnc) v="linuxcnc-uspace $(dpkg-query -W -f='${Version}' linuxcnc-uspace), linuxcnc-uspace-dev $(dpkg-query -W -f='${Version}' linuxcnc-uspace-dev)" ;;
    postgresql) v="postgresql $(dpkg-query -W -f='${Version}' postgresql)" ;;
    mosquitto) v="mosquitto $(dpkg-query -W -f='${Version}' mosquitto)" ;;
    aqdefreader) v="aqdefreader $(aqdef_version) with pandas $("$AQDEF_PREFIX/bin/python" -c 'import pandas; print(pandas.__version__)')" ;;
  esac
  log "version $p: $v"
done
log "done (${peers[*]}) in $(since "$T_ALL")"
