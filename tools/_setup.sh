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
HIL_DEFAULT_EXTRAS="dev,report,console,igtl,campaign-dask"

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
    # Reinstall only when pyproject.toml or the extras changed since the last install.
    local want
    want="$(sha256sum "$HIL_ROOT/pyproject.toml" | cut -d' ' -f1) $extras"
    if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
        log "installing the project into $VENV (extras: $extras)"
        local pip_log="$VENV/pip-install.log"
        if ! { "$VENV/bin/python" -m pip install --upgrade pip &&
               "$VENV/bin/python" -m pip install -e "$HIL_ROOT[$extras]"; } >"$pip_log" 2>&1; then
            log "pip install failed; the last lines of $pip_log:"
            grep -v "is ignored: it is neither a file nor a directory" "$pip_log" | tail -n 30 >&2
            return 1
        fi
        echo "$want" > "$stamp"
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
