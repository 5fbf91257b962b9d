# Shared set-up of scripts/test and scripts/demo: system packages and the project venv.
# Source it after setting: PYTHON, VENV, APT_PACKAGES (array), REQUIRED_TOOLS (array),
# VENV_EXTRAS (pip extras, e.g. "[dev]" or ""), and optionally NEED_UML=1.
# shellcheck shell=bash

have_vcan0() { ip link show vcan0 >/dev/null 2>&1; }

missing_system_tools() {
    local missing=() tool
    command -v "$PYTHON" >/dev/null || missing+=("$PYTHON")
    "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1 || missing+=("$PYTHON venv/ensurepip")
    for tool in "${REQUIRED_TOOLS[@]}"; do
        command -v "$tool" >/dev/null || missing+=("$tool")
    done
    if [[ ${NEED_UML:-0} == 1 ]] && ! have_vcan0; then
        command -v linux.uml >/dev/null || missing+=(linux.uml)
    fi
    printf '%s\n' "${missing[@]}"
}

install_system_packages() {
    local missing
    missing=$(missing_system_tools)
    if [[ -z $missing ]]; then
        echo "all system tools present; apt skipped"
        return 0
    fi
    echo "missing: $(echo "$missing" | paste -sd, -)"
    local sudo=()
    if [[ $(id -u) -ne 0 ]]; then
        command -v sudo >/dev/null || { echo "not root and no sudo: install ${APT_PACKAGES[*]}"; return 1; }
        sudo=(sudo)
    fi
    "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -q
    "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
        --no-install-recommends "${APT_PACKAGES[@]}"
    missing=$(missing_system_tools)
    [[ -z $missing ]] || { echo "still missing after apt-get: $missing"; return 1; }
}

venv_is_usable() {
    [[ -x $VENV/bin/python ]] &&
        "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null
}

prepare_venv() {
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        { echo "$PYTHON is older than 3.11 (set PYTHON=...)"; return 1; }
    if ! venv_is_usable; then
        echo "creating $VENV with $("$PYTHON" --version)"
        "$PYTHON" -m venv --clear "$VENV"
    fi
    # Reinstall only when the dependency declaration or the interpreter changed.
    local stamp_file=$VENV/.bmsid-install-stamp stamp
    stamp="$(sha256sum pyproject.toml | cut -d' ' -f1) $("$VENV/bin/python" --version) ${VENV_EXTRAS}"
    if [[ ${BMSID_REFRESH_VENV:-0} == 1 || ! -f $stamp_file || $(cat "$stamp_file") != "$stamp" ]]; then
        "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off \
            -e ".${VENV_EXTRAS}"
        printf '%s\n' "$stamp" >"$stamp_file"
    else
        echo "$VENV is up to date with pyproject.toml"
    fi
}

