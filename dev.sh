#!/usr/bin/env bash
# One entry point for a fresh machine: each command creates (or reuses) the virtual
# environment in .venv, installs the project and what it needs, then runs.
#   ./dev.sh run     the main job: oralnavd on the embedded simulation default (--demo)
#   ./dev.sh test    lint + the layer rules (import-linter) + the whole test suite (what CI
#                    runs), one pytest worker per core
#   ./dev.sh bench   the benchmarks (long; writes bench/out/)
set -euo pipefail
cd "$(dirname "$0")"
VENV="${ORALNAV_VENV:-.venv}"

setup() {
    if ! command -v python3 >/dev/null; then
        echo "dev.sh: python3 (>= 3.11) is required" >&2; exit 1
    fi
    python3 - <<'PY' || { echo "dev.sh: python3 >= 3.11 is required" >&2; exit 1; }
import sys; sys.exit(sys.version_info < (3, 11))
PY
    if [ ! -x "$VENV/bin/python" ]; then
        echo "dev.sh: creating $VENV" >&2
        python3 -m venv "$VENV"
    fi
    # The Aravis camera backend (PyGObject, built here from source) needs Debian packages;
    # without them oralnav installs without it and its tests are skipped, saying why.
    # test and bench: the suite runs the benchmarks' quick modes and figure commands;
    # cluster: it runs a sweep on a Dask LocalCluster too.
    local extras="test,bench,cluster"
    if aravis_system_packages; then
        extras="test,bench,cluster,aravis"
    fi
    # Reinstall only when pyproject.toml (or the extras installed) changes.
    local stamp="$VENV/.oralnav-$(sha1sum pyproject.toml | cut -c1-12)-${extras//,/-}"
    if [ ! -f "$stamp" ]; then
        echo "dev.sh: installing oralnav[$extras] and its dependencies into $VENV" \
             "(a few minutes the first time)" >&2
        # pip's output (progress, and warnings of the machine's own package-index
        # settings) is kept out of the way, and shown in full only when it fails
        local log
        log="$(mktemp)"
        if ! { "$VENV/bin/python" -m pip install -q --upgrade pip \
               && "$VENV/bin/python" -m pip install -q -e ".[$extras]"; } >"$log" 2>&1; then
            cat "$log" >&2
            rm -f "$log"
            echo "dev.sh: installing oralnav[$extras] failed (pip's output above)" >&2
            exit 1
        fi
        rm -f "$log"
        rm -f "$VENV"/.oralnav-*
        touch "$stamp"
    fi
}

# Debian packages of the Aravis backend: Aravis 0.8's introspection data, its simulated
# GigE Vision camera (for the tests), and what PyGObject and pycairo build against. Installs
# the missing ones with apt-get when run as root; returns 1 (with a message) if some stay
# missing.
aravis_system_packages() {
    local wanted=(gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev
                  pkg-config)
    command -v cc >/dev/null || wanted+=(gcc)
    "${VENV}/bin/python" - <<'PY' || wanted+=(python3-dev)
import os, sys, sysconfig
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))
PY
    if ! command -v dpkg-query >/dev/null; then
        echo "dev.sh: not a Debian system: the Aravis camera backend (Aravis 0.8 with" \
             "GObject introspection, PyGObject) is not installed; its tests are skipped" >&2
        return 1
    fi
    local missing=() pkg
    for pkg in "${wanted[@]}"; do
        [[ "$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null)" == *"ok installed" ]] \
            || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "dev.sh: the Aravis camera backend needs the Debian packages ${missing[*]}" \
             "(run this as root, or: sudo apt-get install ${missing[*]}); until then it is" \
             "not installed and its tests are skipped" >&2
        return 1
    fi
    echo "dev.sh: installing ${missing[*]} with apt-get (Aravis camera backend)" >&2
    export DEBIAN_FRONTEND=noninteractive
    # (set -e does not reach into a function run as an if condition: fail explicitly)
    local log
    log="$(mktemp)"
    if ! { apt-get update -q && apt-get install -y -q --no-install-recommends \
           "${missing[@]}"; } >"$log" 2>&1; then
        cat "$log" >&2  # quiet unless it fails
        rm -f "$log"
        echo "dev.sh: apt-get could not install ${missing[*]}" >&2
        exit 1
    fi
    rm -f "$log"
}

# Debian's chromium, its chromedriver and a font, for the console's browser tests
# (Selenium drives them; nothing is downloaded from a browser vendor). Installed with
# apt-get when run as root; otherwise (or off Debian) the browser tests are skipped,
# saying why.
browser_packages() {
    command -v dpkg-query >/dev/null || return 0
    local missing=() pkg
    for pkg in chromium chromium-driver fonts-liberation; do
        [[ "$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null)" == *"ok installed" ]] \
            || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "dev.sh: the console's browser tests need ${missing[*]} (sudo apt-get install" \
             "${missing[*]}); until then they are skipped" >&2
        return 0
    fi
    echo "dev.sh: installing ${missing[*]} with apt-get (the console's browser tests)" >&2
    local log
    log="$(mktemp)"
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -q \
           && DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
                --no-install-recommends "${missing[@]}"; } >"$log" 2>&1; then
        cat "$log" >&2
        echo "dev.sh: apt-get could not install ${missing[*]}: the browser tests will be" \
             "skipped" >&2
    fi
    rm -f "$log"
}

cmd="${1:-}"
shift || true
case "$cmd" in
    run)
        setup
        # ./dev.sh run -- --record out/demo.mcap: what follows "--" goes to oralnavd
        [ "${1:-}" = "--" ] && shift
        exec "$VENV/bin/oralnavd" --demo "$@"
        ;;
    test)
        setup
        browser_packages
        "$VENV/bin/ruff" check .
        "$VENV/bin/python" -m tests.layers
        # one pytest worker per core (pytest-xdist): the suite is mostly independent
        # CPU-bound tests. Each module stays on one worker (loadscope), so a module's
        # shared fixtures (rendered views, calibrations) are built once: 9:13 against 10:15
        # split test by test, on 2 cores. ORALNAV_TEST_WORKERS=0 runs it in one process.
        # Then the tests marked "alone" (the hardware-in-the-loop demo and the console in a
        # browser: their renderer and daemon starve beside another worker on 2 cores),
        # with nothing beside them; exit 5 there means none was selected.
        rc=0 rc_alone=0
        "$VENV/bin/python" -m pytest -n "${ORALNAV_TEST_WORKERS:-auto}" --dist loadscope \
            -m "not alone" "$@" || rc=$?
        "$VENV/bin/python" -m pytest -m alone "$@" || rc_alone=$?
        [ "$rc_alone" -eq 5 ] && rc_alone=0
        [ "$rc" -ne 0 ] && exit "$rc"
        exit "$rc_alone"
        ;;
    bench)
        setup
        exec "$VENV/bin/python" -m bench "$@"
        ;;
    *)
        echo "usage: ./dev.sh run | test | bench" >&2
        exit 2
        ;;
esac
