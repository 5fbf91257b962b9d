#!/usr/bin/env bash
# Set up a SocketCAN interface by hand (what deploy/networkd/ does at boot). Idempotent: an
# interface that is already as asked is left alone.
#
#   vcan-setup.sh [vcan0]                 virtual CAN (replays, tests): modprobe vcan,
#                                         ip link add dev vcan0 type vcan, ip link set up vcan0
#   vcan-setup.sh can0 [--bitrate 500000] [--sample-point 0.875] [--restart-ms 100]
#                                         real CAN: ip link set can0 down; ip link set can0 type
#                                         can bitrate ... restart-ms ...; ip link set can0 up
# Options: --dry-run (print the commands, change nothing), -h/--help.
# Exit codes: 0 done (or nothing to do), 1 failed, 2 bad usage.

set -euo pipefail

PROG=$(basename "$0")
usage() {
    cat <<EOF
Usage: $PROG [OPTIONS] [INTERFACE]

Bring up a SocketCAN interface. Needs root (or CAP_NET_ADMIN); idempotent.

  INTERFACE starting with "vcan" (default vcan0): create the virtual CAN interface if missing
      (modprobe vcan; ip link add dev NAME type vcan) and set it up.
  any other INTERFACE (can0, can1, ...): a real CAN controller; set the bit timing and the
      bus-off auto-restart, then set it up:
      ip link set NAME down; ip link set NAME type can bitrate B sample-point S restart-ms R;
      ip link set NAME up
      (skipped when NAME is already up with that bitrate and restart-ms).

Options (real CAN only, except --dry-run):
  --bitrate B        bit/s (default 500000)
  --sample-point S   0.000..0.999 (default 0.875, CiA 301 at 500 kbit/s; 0 = driver default)
  --restart-ms R     bus-off auto-restart delay, ms (default 100; 0 = off)
  --dry-run          print the commands that would run, change nothing
  -h, --help         show this help

Check the result: ip -details -statistics link show INTERFACE
EOF
}

die() {
    printf '%s: error: %s\n' "$PROG" "$*" >&2
    exit 1
}
usage_error() {
    printf '%s: %s (see --help)\n' "$PROG" "$*" >&2
    exit 2
}
say() { printf '%s: %s\n' "$PROG" "$*"; }

IFACE=""
BITRATE=500000
SAMPLE_POINT=0.875
RESTART_MS=100
DRY_RUN=0
while [[ $# -gt 0 ]]; do
    case $1 in
        -h | --help)
            usage
            exit 0
            ;;
        --bitrate) [[ $# -ge 2 ]] || usage_error "--bitrate needs a value"; BITRATE=$2; shift 2 ;;
        --bitrate=*) BITRATE=${1#*=}; shift ;;
        --sample-point) [[ $# -ge 2 ]] || usage_error "--sample-point needs a value"; SAMPLE_POINT=$2; shift 2 ;;
        --sample-point=*) SAMPLE_POINT=${1#*=}; shift ;;
        --restart-ms) [[ $# -ge 2 ]] || usage_error "--restart-ms needs a value"; RESTART_MS=$2; shift 2 ;;
        --restart-ms=*) RESTART_MS=${1#*=}; shift ;;
        --dry-run) DRY_RUN=1; shift ;;
        -*) usage_error "unknown option: $1" ;;
        *)
            [[ -z $IFACE ]] || usage_error "one interface only (got $IFACE and $1)"
            IFACE=$1
            shift
            ;;
    esac
done
IFACE=${IFACE:-vcan0}

[[ $IFACE =~ ^[A-Za-z0-9_.-]{1,15}$ ]] || usage_error "not an interface name: '$IFACE'"
[[ $BITRATE =~ ^[1-9][0-9]*$ ]] || usage_error "--bitrate must be a positive integer (bit/s), got '$BITRATE'"
[[ $RESTART_MS =~ ^[0-9]+$ ]] || usage_error "--restart-ms must be an integer >= 0, got '$RESTART_MS'"
[[ $SAMPLE_POINT =~ ^0(\.[0-9]{1,3})?$ ]] ||
    usage_error "--sample-point must be 0 or 0.xxx (e.g. 0.875), got '$SAMPLE_POINT'"

# ip and modprobe live in sbin, which a non-root PATH may lack.
export PATH="$PATH:/usr/local/sbin:/usr/sbin:/sbin"
command -v ip >/dev/null || die "'ip' not found: apt-get install iproute2"

# run CMD...: run it, or only print it with --dry-run.
run() {
    if [[ $DRY_RUN == 1 ]]; then
        printf '+ %s\n' "$*"
        return 0
    fi
    printf '+ %s\n' "$*"
    "$@"
}

if [[ $DRY_RUN == 0 && $(id -u) -ne 0 ]]; then
    die "configuring $IFACE needs root (sudo $0 ...) or CAP_NET_ADMIN; --dry-run shows the commands"
fi

link_details() { ip -details link show dev "$IFACE" 2>/dev/null; }
link_is_up() { link_details | head -n 1 | grep -q '[<,]UP[,>]'; }

setup_vcan() {
    local details
    if details=$(link_details); then
        grep -qw vcan <<<"$details" ||
            die "$IFACE exists but is not a vcan interface: $(head -n 1 <<<"$details")"
        if link_is_up; then
            say "$IFACE is already a vcan interface and up: nothing to do"
            return 0
        fi
    else
        if [[ ! -d /sys/module/vcan ]]; then
            command -v modprobe >/dev/null || die "'modprobe' not found: apt-get install kmod"
            run modprobe vcan ||
                die "modprobe vcan failed: this kernel has no vcan module (a container or a minimal kernel?)"
        fi
        run ip link add dev "$IFACE" type vcan || die "ip link add dev $IFACE type vcan failed"
    fi
    run ip link set up "$IFACE" || die "ip link set up $IFACE failed"
    [[ $DRY_RUN == 1 ]] || say "$IFACE is up"
}

setup_can() {
    local details type_args
    details=$(link_details) ||
        die "no interface $IFACE: plug in / load the CAN adapter's driver (ip link show lists the interfaces)"
    grep -qw 'can' <<<"$details" ||
        die "$IFACE is not a CAN controller: $(head -n 1 <<<"$details")"
    grep -qw vcan <<<"$details" &&
        die "$IFACE is a vcan interface: it has no bit rate (use $PROG $IFACE without a real-CAN name)"
    if link_is_up && grep -qw "bitrate $BITRATE" <<<"$details" &&
        grep -qw "restart-ms $RESTART_MS" <<<"$details"; then
        say "$IFACE is already up at $BITRATE bit/s with restart-ms $RESTART_MS: nothing to do"
        return 0
    fi
    type_args=(bitrate "$BITRATE" restart-ms "$RESTART_MS")
    if [[ $SAMPLE_POINT != 0 ]]; then
        type_args+=(sample-point "$SAMPLE_POINT")
    fi
    # The bit timing can only be changed while the interface is down.
    run ip link set "$IFACE" down || die "ip link set $IFACE down failed"
    run ip link set "$IFACE" type can "${type_args[@]}" ||
        die "ip link set $IFACE type can ${type_args[*]} failed (bit rate not supported by the controller?)"
    run ip link set "$IFACE" up || die "ip link set $IFACE up failed"
    [[ $DRY_RUN == 1 ]] || say "$IFACE is up: $(ip -details link show dev "$IFACE" | grep -o 'bitrate [0-9]* sample-point [0-9.]*' || true)"
}

if [[ $IFACE == vcan* ]]; then
    setup_vcan
else
    setup_can
fi
