#!/usr/bin/env bash
# Set up graphopt on a fresh Debian machine: system SuiteSparse (if permitted), a virtual
# environment in .venv, and the package with its test extras. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}

# CHOLMOD comes from scikit-sparse, which compiles against SuiteSparse's headers.
have_suitesparse() { [ -f /usr/include/suitesparse/cholmod.h ]; }
if ! have_suitesparse && command -v apt-get >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then
        echo "bootstrap: installing libsuitesparse-dev (for CHOLMOD)"
        (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libsuitesparse-dev >/dev/null) \
            || echo "bootstrap: could not install libsuitesparse-dev; graphopt will use another linear solver"
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        (sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libsuitesparse-dev >/dev/null) \
            || echo "bootstrap: could not install libsuitesparse-dev; graphopt will use another linear solver"
    else
        echo "bootstrap: libsuitesparse-dev is missing and cannot be installed without root; CHOLMOD will be unavailable"
    fi
fi

# -P: never put the checkout on sys.path, where types/ would shadow the standard library.
[ -x "$VENV/bin/python" ] || "$PY" -P -m venv "$VENV"
"$VENV/bin/python" -P -m pip install -q --upgrade pip >/dev/null
"$VENV/bin/python" -P -m pip install -q -e ".[test]"
if have_suitesparse; then
    "$VENV/bin/python" -P -m pip install -q "scikit-sparse>=0.4.16,<0.5" \
        || echo "bootstrap: scikit-sparse failed to build; graphopt will use another linear solver"
fi
