#!/usr/bin/env bash
# Install bmsid on a gateway: venv, systemd unit, config, examples. See deploy/README.md.
#
#   sudo deploy/install.sh [OPTIONS] [SOURCE]
#
# SOURCE is what pip installs into /opt/bmsid/venv: a bmsid wheel (.whl) or a source
# checkout; default: the checkout this script belongs to.
#
# What it does, in order (every step is safe to repeat):
#   1. /opt/bmsid/venv: created with PYTHON -m venv if missing, then pip installs SOURCE
#      (with its dependencies, from the package index unless --pip-option says otherwise).
#   2. /etc/systemd/system/bmsid.service: the unit, always replaced (site changes belong in a
#      drop-in: systemctl edit bmsid).
#   3. /etc/bmsid/bmsid.toml: the example config, ONLY if there is none. An existing config is
#      never touched; when it differs from this version's example, the example is written
#      beside it as bmsid.toml.new to compare with.
#   4. /etc/bmsid/mqtt.password: created EMPTY (root, 0600) if missing, because the unit loads
#      it as a systemd credential and a missing file would stop the service from starting.
#   5. /usr/share/doc/bmsid: deploy/README.md and examples (Mosquitto config and ACL,
#      networkd files, Node-RED flow, cell configs, the example config).
#      /opt/bmsid/bin/vcan-setup.sh: the CAN interface helper.
#   6. with --networkd: /etc/systemd/network/80-can0.network (same rule as the config: an
#      existing, different file is kept and the new one goes to *.new);
#      with --networkd-vcan: 80-vcan0.netdev and 80-vcan0.network (replays, test benches).
#   7. systemctl daemon-reload (and, with --networkd*, enable systemd-networkd and reload it),
#      unless --no-systemctl or --root is given.
# It does not enable or start bmsid: it prints the commands for that.

set -euo pipefail

usage() {
    cat <<'EOF'
Usage: install.sh [OPTIONS] [SOURCE]

Install bmsid: venv in /opt/bmsid/venv, systemd unit, /etc/bmsid/bmsid.toml (only if absent),
examples in /usr/share/doc/bmsid. SOURCE: a bmsid wheel or source checkout (default: this
checkout). Safe to run again to upgrade: an existing config is never overwritten.

Options:
  --root DIR          install below DIR instead of / (staging, tests); implies --no-systemctl.
                      The venv is created at DIR/opt/bmsid/venv and only works there (venvs
                      cannot be moved): for a chroot, run install.sh inside it.
  --python PY         interpreter for a new venv (default: python3; needs >= 3.11 and venv)
  --pip-option OPT    pass OPT to pip install (repeatable), e.g. --pip-option=--no-index
                      --pip-option=--find-links=/srv/wheels for an offline install
  --link-venv DIR     do not create a venv: make /opt/bmsid/venv a symlink to DIR, an existing
                      venv with bmsid installed (it must not live under /home, /root or /tmp,
                      which the unit hides from the service)
  --networkd          also install the systemd-networkd file for can0 (500 kbit/s, restart-ms 100)
  --networkd-vcan     also install the systemd-networkd files that create vcan0
  --no-systemctl      do not run systemctl
  -h, --help          show this help
EOF
}

die() {
    printf 'install.sh: error: %s\n' "$*" >&2
    exit 1
}
say() { printf 'install.sh: %s\n' "$*"; }

DEPLOY_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd -P)
REPO_DIR=$(dirname "$DEPLOY_DIR")

ROOT=/
PYTHON=python3
PIP_OPTIONS=()
LINK_VENV=""
NETWORKD=0
NETWORKD_VCAN=0
RUN_SYSTEMCTL=1
SOURCE=""

while [[ $# -gt 0 ]]; do
    case $1 in
        -h | --help)
            usage
            exit 0
            ;;
        --root) [[ $# -ge 2 ]] || die "--root needs a directory"; ROOT=$2; shift 2 ;;
        --root=*) ROOT=${1#*=}; shift ;;
        --python) [[ $# -ge 2 ]] || die "--python needs an interpreter"; PYTHON=$2; shift 2 ;;
        --python=*) PYTHON=${1#*=}; shift ;;
        --pip-option) [[ $# -ge 2 ]] || die "--pip-option needs a value"; PIP_OPTIONS+=("$2"); shift 2 ;;
        --pip-option=*) PIP_OPTIONS+=("${1#*=}"); shift ;;
        --link-venv) [[ $# -ge 2 ]] || die "--link-venv needs a directory"; LINK_VENV=$2; shift 2 ;;
        --link-venv=*) LINK_VENV=${1#*=}; shift ;;
        --networkd) NETWORKD=1; shift ;;
        --networkd-vcan) NETWORKD_VCAN=1; shift ;;
        --no-systemctl) RUN_SYSTEMCTL=0; shift ;;
        --) shift; break ;;
        -*) usage >&2; die "unknown option: $1" ;;
        *)
            [[ -z $SOURCE ]] || die "only one SOURCE may be given (got $SOURCE and $1)"
            SOURCE=$1
            shift
            ;;
    esac
done
if [[ $# -gt 0 ]]; then
    [[ -z $SOURCE && $# -eq 1 ]] || die "only one SOURCE may be given"
    SOURCE=$1
fi

# ---------------------------------------------------------------------------------------------
# Checks before anything is written.
# ---------------------------------------------------------------------------------------------
[[ -d $ROOT ]] || die "--root $ROOT: no such directory"
ROOT=$(cd "$ROOT" && pwd -P)
if [[ $ROOT != / ]]; then
    RUN_SYSTEMCTL=0
fi
dest() { # dest /etc/x -> $ROOT/etc/x
    if [[ $ROOT == / ]]; then printf '%s\n' "$1"; else printf '%s%s\n' "$ROOT" "$1"; fi
}
if [[ $ROOT == / && $(id -u) -ne 0 ]]; then
    die "installing to / needs root (sudo $0 ...), or use --root DIR for a staging directory"
fi

for f in systemd/bmsid.service mosquitto/bmsid.conf mosquitto/bmsid.acl \
    networkd/80-can0.network networkd/80-vcan0.netdev networkd/80-vcan0.network \
    dashboard/node-red-flow.json vcan-setup.sh README.md; do
    [[ -f $DEPLOY_DIR/$f ]] || die "missing $DEPLOY_DIR/$f: run install.sh from a complete bmsid tree"
done
EXAMPLE_CONFIG=$REPO_DIR/configs/bmsid.example.toml
[[ -f $EXAMPLE_CONFIG ]] || die "missing $EXAMPLE_CONFIG: run install.sh from a complete bmsid tree"

if [[ -n $LINK_VENV ]]; then
    [[ -z $SOURCE ]] || die "--link-venv and SOURCE exclude each other (nothing is pip-installed)"
    [[ -x $LINK_VENV/bin/bmsid ]] || die "--link-venv $LINK_VENV: no bin/bmsid in it"
    LINK_VENV=$(cd "$LINK_VENV" && pwd -P)
else
    SOURCE=${SOURCE:-$REPO_DIR}
    if [[ -d $SOURCE ]]; then
        [[ -f $SOURCE/pyproject.toml ]] || die "SOURCE $SOURCE: a directory without pyproject.toml"
        SOURCE=$(cd "$SOURCE" && pwd -P)
    elif [[ -f $SOURCE ]]; then
        [[ $SOURCE == *.whl ]] || die "SOURCE $SOURCE: not a wheel (.whl) or a source directory"
        SOURCE=$(cd "$(dirname "$SOURCE")" && pwd -P)/$(basename "$SOURCE")
    else
        die "SOURCE $SOURCE: no such file or directory"
    fi
    command -v "$PYTHON" >/dev/null || die "python interpreter '$PYTHON' not found (apt-get install python3)"
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        die "$PYTHON is $("$PYTHON" --version 2>&1); bmsid needs Python >= 3.11 (use --python)"
    "$PYTHON" -c 'import ensurepip, venv' 2>/dev/null ||
        die "$PYTHON cannot create venvs: apt-get install python3-venv"
fi

# ---------------------------------------------------------------------------------------------
# Helpers.
# ---------------------------------------------------------------------------------------------

# install_file SRC DEST MODE: copy, replacing DEST (our own files: unit, docs, examples).
install_file() {
    local src=$1 target=$2 mode=$3
    mkdir -p "$(dirname "$target")"
    if [[ -f $target ]] && cmp -s "$src" "$target"; then
        chmod "$mode" "$target"
        return 0
    fi
    install -m "$mode" "$src" "$target"
    say "installed $target"
}

# install_config SRC DEST MODE: the operator's files (config, networkd). Written only if DEST
# is absent; an existing different DEST is kept and SRC goes to DEST.new.
install_config() {
    local src=$1 target=$2 mode=$3
    mkdir -p "$(dirname "$target")"
    if [[ ! -e $target ]]; then
        install -m "$mode" "$src" "$target"
        say "installed $target"
    elif cmp -s "$src" "$target"; then
        say "kept $target (same as this version's)"
        rm -f "$target.new"
    else
        install -m "$mode" "$src" "$target.new"
        say "kept $target (edited): this version's file is $target.new; compare with" \
            "diff -u $target $target.new"
    fi
}

# ---------------------------------------------------------------------------------------------
# 1. The venv.
# ---------------------------------------------------------------------------------------------
VENV=$(dest /opt/bmsid/venv)
mkdir -p "$(dirname "$VENV")"
if [[ -n $LINK_VENV ]]; then
    if [[ -L $VENV || ! -e $VENV ]]; then
        ln -sfn "$LINK_VENV" "$VENV"
        say "linked $VENV -> $LINK_VENV"
    else
        die "$VENV exists and is not a symlink: remove it to use --link-venv"
    fi
else
    if [[ -L $VENV ]]; then
        rm "$VENV"
        say "removed the symlink $VENV (a real venv replaces it)"
    fi
    if [[ ! -x $VENV/bin/python ]]; then
        say "creating $VENV with $("$PYTHON" --version 2>&1)"
        "$PYTHON" -m venv "$VENV"
    fi
    "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        die "$VENV has $("$VENV/bin/python" --version 2>&1); remove it and run again with --python"
    say "pip install $SOURCE into $VENV"
    # --upgrade: a newer wheel or checkout replaces the installed bmsid; --force-reinstall
    # --no-deps afterwards: the same version number built from newer sources replaces it too
    # (pip would call it "already satisfied").
    "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off \
        "${PIP_OPTIONS[@]}" --upgrade "$SOURCE"
    "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off \
        "${PIP_OPTIONS[@]}" --force-reinstall --no-deps "$SOURCE"
fi
[[ -x $VENV/bin/bmsid ]] || die "$VENV/bin/bmsid is missing"
version=$("$VENV/bin/python" -c 'import bmsid.cli.main, bmsid; print(bmsid.__version__)') ||
    die "bmsid does not import in $VENV"
say "bmsid $version in $VENV"

# ---------------------------------------------------------------------------------------------
# 2.-4. Unit, config, credential file.
# ---------------------------------------------------------------------------------------------
install_file "$DEPLOY_DIR/systemd/bmsid.service" "$(dest /etc/systemd/system/bmsid.service)" 0644
mkdir -p "$(dest /etc/bmsid)"
chmod 0755 "$(dest /etc/bmsid)"
install_config "$EXAMPLE_CONFIG" "$(dest /etc/bmsid/bmsid.toml)" 0644
PASSWORD_FILE=$(dest /etc/bmsid/mqtt.password)
if [[ ! -e $PASSWORD_FILE ]]; then
    (umask 077 && : >"$PASSWORD_FILE")
    say "created an empty $PASSWORD_FILE (0600): put the MQTT password in it if the broker needs one"
fi

# ---------------------------------------------------------------------------------------------
# 5. Documentation, examples, helper.
# ---------------------------------------------------------------------------------------------
DOC=$(dest /usr/share/doc/bmsid)
install_file "$DEPLOY_DIR/README.md" "$DOC/README.md" 0644
install_file "$EXAMPLE_CONFIG" "$DOC/examples/bmsid.example.toml" 0644
for f in mosquitto/bmsid.conf mosquitto/bmsid.acl networkd/80-can0.network \
    networkd/80-vcan0.netdev networkd/80-vcan0.network dashboard/node-red-flow.json; do
    install_file "$DEPLOY_DIR/$f" "$DOC/examples/$f" 0644
done
for f in "$REPO_DIR"/configs/cells/*.toml; do
    [[ -e $f ]] && install_file "$f" "$DOC/examples/cells/$(basename "$f")" 0644
done
install_file "$DEPLOY_DIR/vcan-setup.sh" "$(dest /opt/bmsid/bin/vcan-setup.sh)" 0755

# ---------------------------------------------------------------------------------------------
# 6. systemd-networkd (optional).
# ---------------------------------------------------------------------------------------------
NETWORK_DIR=$(dest /etc/systemd/network)
if [[ $NETWORKD == 1 ]]; then
    install_config "$DEPLOY_DIR/networkd/80-can0.network" "$NETWORK_DIR/80-can0.network" 0644
fi
if [[ $NETWORKD_VCAN == 1 ]]; then
    install_config "$DEPLOY_DIR/networkd/80-vcan0.netdev" "$NETWORK_DIR/80-vcan0.netdev" 0644
    install_config "$DEPLOY_DIR/networkd/80-vcan0.network" "$NETWORK_DIR/80-vcan0.network" 0644
fi

# ---------------------------------------------------------------------------------------------
# 7. systemd.
# ---------------------------------------------------------------------------------------------
if [[ $RUN_SYSTEMCTL == 1 ]]; then
    systemctl daemon-reload
    say "systemctl daemon-reload done"
    if [[ $NETWORKD == 1 || $NETWORKD_VCAN == 1 ]]; then
        systemctl enable --now systemd-networkd.service
        networkctl reload
        say "systemd-networkd enabled and reloaded (networkctl status can0)"
    fi
    if systemctl is-active --quiet bmsid.service; then
        say "bmsid is running the previous version: systemctl restart bmsid"
    fi
else
    say "systemctl skipped (--no-systemctl or --root)"
fi

cat <<EOF

Next steps:
  1. edit /etc/bmsid/bmsid.toml (pack_id, can.n_cells, mqtt.url, mqtt.username), then check it:
       /opt/bmsid/venv/bin/bmsid check-config /etc/bmsid/bmsid.toml
  2. MQTT password (if the broker needs one): /etc/bmsid/mqtt.password (root, 0600)
  3. CAN interface: deploy/README.md "CAN interface" (install.sh --networkd, or
       /opt/bmsid/bin/vcan-setup.sh can0)
  4. systemctl enable --now bmsid && journalctl -u bmsid -f
EOF
