# shellcheck shell=bash
# Shared set-up for tools/run and tools/test: creates .venv when missing and installs the project
# into it (editable, with the dev extras). Debian packages that optional features need are
# installed with apt-get when we are root and they are missing. Sourced, not executed.
set -euo pipefail

HIL_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${HIL_VENV:-$HIL_ROOT/.venv}"
PY="${PYTHON:-python3}"

# Extras every set-up installs: dev tools, the report/console/OpenIGTLink features, and the Dask
# executor of the fault campaigns.
HIL_DEFAULT_EXTRAS="dev,report,console,igtl,campaign-dask,viewer"

log() { printf '[setup] %s\n' "$*" >&2; }

apt_install_missing() {
    # apt_install_missing PKG... : installs the packages dpkg does not know, when root.
    local missing=()
    for pkg in "$@"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    if [ "$(id -u)" != "0" ]; then
        log "missing Debian packages (${missing[*]}); not root, so not installing them"
        return 1
    fi
    log "apt-get install ${missing[*]}"
    if [ -z "${HIL_APT_UPDATED:-}" ]; then
        DEBIAN_FRONTEND=noninteractive apt-get update -qq >&2
        export HIL_APT_UPDATED=1
    fi
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2
}

ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        log "creating $VENV"
        "$PY" -m venv "$VENV"
    fi
    local stamp="$VENV/.hil-installed"
    local extras="${HIL_EXTRAS:-$HIL_DEFAULT_EXTRAS}"
    # Reinstall only when pyproject.toml, setup.py, the C sources of the compiled kernels
    # (hil/vision/_kernel.c, hil/geometry/_native.c) or the extras changed since the last install,
    # or a built kernel is gone (the editable install builds them next to their sources).
    local want
    want="$(cat "$HIL_ROOT/pyproject.toml" "$HIL_ROOT/setup.py" "$HIL_ROOT"/hil/vision/*.c "$HIL_ROOT"/hil/geometry/*.c |
            sha256sum | cut -d' ' -f1) $extras"
    if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] ||
       ! compgen -G "$HIL_ROOT/hil/vision/_kernel*.so" >/dev/null ||
       ! compgen -G "$HIL_ROOT/hil/geometry/_native*.so" >/dev/null; then
        ensure_c_compiler || return 1
        log "installing the project into $VENV (extras: $extras)"
        local pip_log="$VENV/pip-install.log"
        if ! { "$VENV/bin/python" -m pip install --upgrade pip &&
               "$VENV/bin/python" -m pip install -e "$HIL_ROOT[$extras]"; } >"$pip_log" 2>&1; then
            if grep -qE "(_kernel|_native).c:[0-9]*:[0-9]*: error" "$pip_log"; then
                log "building a compiled kernel (hil/vision/_kernel.c, hil/geometry/_native.c) failed; the compiler's errors (all in $pip_log):"
                grep -m 10 -E "(_kernel|_native).c:[0-9]*:[0-9]*: error" "$pip_log" >&2
                return 1
            fi
            log "pip install failed; the last lines of $pip_log:"
            grep -v "is ignored: it is neither a file nor a directory" "$pip_log" | tail -n 30 >&2
            return 1
        fi
        echo "$want" > "$stamp"
    fi
}

ensure_c_compiler() {
    # The editable install compiles hil/vision/_kernel.c and hil/geometry/_native.c: it needs a C
    # compiler (Debian gcc) and the Python headers (pyenv builds have them; Debian's own python3
    # needs python3-dev).
    if ! command -v "${CC:-gcc}" >/dev/null 2>&1; then
        apt_install_missing gcc libc6-dev || true
        if ! command -v "${CC:-gcc}" >/dev/null 2>&1; then
            log "no C compiler (gcc) to build the compiled kernels (hil/vision/_kernel.c, hil/geometry/_native.c): install gcc (apt-get install gcc)"
            return 1
        fi
    fi
    local include
    include="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    if [ ! -f "$include/Python.h" ]; then
        apt_install_missing python3-dev || true
        if [ ! -f "$include/Python.h" ]; then
            log "no Python headers ($include/Python.h) to build the vision kernel: install python3-dev (Debian's python3) or use a Python built with its headers"
            return 1
        fi
    fi
}

ensure_device_support() {
    # Debian packages for the camera (Aravis) and serial (socat) tests; adds the `aravis` extra
    # when they are present. In CI (CI=true) a failure here is an error: those tests must run.
    source "$HIL_ROOT/tools/setup_aravis.sh"
    if ensure_aravis_apt; then
        HIL_EXTRAS="${HIL_EXTRAS:-$HIL_DEFAULT_EXTRAS},aravis"
        export HIL_EXTRAS
    elif [ "${CI:-}" = "true" ]; then
        log "CI: the Aravis/socat Debian packages could not be installed"
        return 1
    fi
}

ensure_browser() {
    # Debian's chromium for the replay's browser test (tests/replay/test_browser.py: headless,
    # against the Rerun web viewer served on loopback). In CI a failure here is an error.
    if ! apt_install_missing chromium && [ "${CI:-}" = "true" ]; then
        log "CI: the chromium Debian package could not be installed"
        return 1
    fi
    return 0
}
