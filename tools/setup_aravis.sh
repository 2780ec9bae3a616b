#!/usr/bin/env bash
# shellcheck shell=bash
# Aravis (GigE Vision / USB3 Vision cameras) set-up: the Debian packages the camera driver, the fake
# GigE cameras (tools/fakegv, arv-fake-gv-camera-0.8) and the PyGObject build need.
#
# Sourced by tools/_setup.sh (which defines log and apt_install_missing):
#     source "$HIL_ROOT/tools/setup_aravis.sh"
#     if ensure_aravis_apt; then HIL_EXTRAS="$HIL_EXTRAS,aravis"; fi    # before ensure_venv
# ensure_aravis_apt installs what is missing when root (apt-get update once), and returns 0 only
# when everything PyGObject==3.50.2 (the `aravis` extra) needs to build and run is present.
#
# Run directly (`tools/setup_aravis.sh`), it does the same and then pip-installs PyGObject==3.50.2
# into the project's virtualenv.
#
# Packages (Debian 12):
#   gir1.2-aravis-0.8 libaravis-0.8-0   the typelib and the library (ctypes fill callback in fakegv)
#   aravis-tools                        arv-fake-gv-camera-0.8 (pulls GTK3; the tests run it)
#   aravis-tools-cli                    arv-tool-0.8 (list/inspect cameras)
#   libgirepository1.0-dev libcairo2-dev pkg-config gcc   build PyGObject 3.50.2 and pycairo
#   python3-dev                         Python.h, only when the interpreter's headers are missing
#   iproute2                            `ip addr add 127.0.0.2/8 dev lo` for the stereo tests
#   socat                               linked pseudo-terminals (tracker emulator tests)

HIL_ARAVIS_APT_PACKAGES=(
    gir1.2-aravis-0.8 libaravis-0.8-0 aravis-tools aravis-tools-cli
    libgirepository1.0-dev libcairo2-dev pkg-config gcc iproute2 socat
)

_aravis_python() {
    if [ -n "${VENV:-}" ] && [ -x "$VENV/bin/python" ]; then
        printf '%s' "$VENV/bin/python"
    else
        printf '%s' "${PY:-${PYTHON:-python3}}"
    fi
}

_aravis_python_headers_present() {
    "$(_aravis_python)" -c 'import os, sysconfig, sys; sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")) else 1)' 2>/dev/null
}

ensure_aravis_apt() {
    local packages=("${HIL_ARAVIS_APT_PACKAGES[@]}")
    _aravis_python_headers_present || packages+=(python3-dev)
    if ! apt_install_missing "${packages[@]}"; then
        log "Aravis camera support not installed (Debian packages missing); the aravis tests will skip"
        return 1
    fi
    return 0
}

_aravis_main() {
    source "$(dirname "${BASH_SOURCE[0]}")/_setup.sh"
    ensure_aravis_apt || exit 1
    ensure_venv
    if "$VENV/bin/python" -c 'import gi; gi.require_version("Aravis", "0.8")' 2>/dev/null; then
        log "PyGObject and the Aravis typelib are already usable in $VENV"
        return 0
    fi
    log "pip install PyGObject==3.50.2 into $VENV"
    "$VENV/bin/python" -m pip install "PyGObject==3.50.2" >&2
    "$VENV/bin/python" -c 'import gi; gi.require_version("Aravis", "0.8"); from gi.repository import Aravis' \
        && log "Aravis is usable from $VENV"
}

# Executed (not sourced): do the whole set-up.
if [ "${BASH_SOURCE[0]}" = "$0" ]; then
    set -euo pipefail
    _aravis_main "$@"
fi
