#!/usr/bin/env bash
# One entry point for a fresh machine: each command creates (or reuses) the virtual
# environment in .venv, installs the project and what it needs, then runs.
#   ./dev.sh run     the main job: oralnavd on the embedded simulation default (--demo)
#   ./dev.sh test    lint + the whole test suite (what CI runs)
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
    # Reinstall only when pyproject.toml changes.
    local stamp="$VENV/.oralnav-$(sha1sum pyproject.toml | cut -c1-12)"
    if [ ! -f "$stamp" ]; then
        echo "dev.sh: installing oralnav and its dependencies into $VENV" >&2
        "$VENV/bin/python" -m pip install -q --upgrade pip >&2
        "$VENV/bin/python" -m pip install -q -e ".[test]" >&2
        rm -f "$VENV"/.oralnav-*
        touch "$stamp"
    fi
}

cmd="${1:-}"
shift || true
case "$cmd" in
    run)
        setup
        exec "$VENV/bin/oralnavd" --demo "$@"
        ;;
    test)
        setup
        "$VENV/bin/ruff" check .
        exec "$VENV/bin/python" -m pytest "$@"
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
