#!/usr/bin/env bash
# One-time set-up on a fresh machine: Debian's libllvm19 (drjit 1.5 crashes with LLVM 15) and a
# virtual environment with the package and its test dependencies. Idempotent: a second run only
# checks. Usage: tools/setup.sh [VENV_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
PY=${PYTHON:-python3}

# 1. libLLVM >= 16, found by the same code that `import mi_twopass` runs.
if ! "$PY" -c "import importlib.util as u, sys; s=u.spec_from_file_location('l','mi_twopass/_llvm.py'); m=u.module_from_spec(s); s.loader.exec_module(m); sys.exit(0 if m.find_libllvm()[0] else 1)"; then
  if [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    echo "setup: no libLLVM >= 16 found; installing Debian's libllvm19" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  fi
fi

# 2. The virtual environment (re-installed when pyproject.toml changes).
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
STAMP="$VENV/.mi_twopass-installed"
if [ ! -f "$STAMP" ] || [ pyproject.toml -nt "$STAMP" ]; then
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -e ".[test]"
  "$VENV/bin/python" -m ipykernel install --sys-prefix --name python3 >/dev/null 2>&1 || true
  touch "$STAMP"
fi
"$VENV/bin/python" -c "import mi_twopass, mitsuba as mi; print('setup: ok,', mi.variant(), 'registered:', mi_twopass.registered_names())"
