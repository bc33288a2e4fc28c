#!/usr/bin/env bash
# Set up graphopt on a fresh Debian machine: system SuiteSparse and Chromium (if permitted), a
# virtual environment in .venv, and the package with its test and browser extras. Safe to run again: when neither
# pyproject.toml, this script nor the checkout's location changed since the last complete set-up
# (a stamp inside .venv records them) and .venv still imports graphopt, it only says so.
#
# pip's output goes to .venv/bootstrap.log; it is printed in full when an installation fails.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
STAMP="$VENV/.bootstrap-stamp"
LOG="$VENV/bootstrap.log"

say() { echo "bootstrap: $*"; }

# CHOLMOD comes from scikit-sparse, which compiles against SuiteSparse's headers. It calls the
# system's libblas.so.3: Debian's reference BLAS makes its supernodal factorisations several
# times slower than OpenBLAS, which registers itself as that library's provider.
have_suitesparse() { [ -f /usr/include/suitesparse/cholmod.h ]; }
have_openblas() { compgen -G "/usr/lib/*/openblas-pthread/libblas.so.3" >/dev/null; }
# The browser test (tests/test_recording_browser.py) opens the apps' recordings in rerun's web
# viewer in Debian's Chromium, driven by Playwright (the `browser` extra); Playwright's own
# browser download is not used.
have_chromium() { [ -x /usr/bin/chromium ]; }

# What the installation depends on. The stamp is written only after a complete set-up.
stamp() {
    echo "checkout $(pwd -P)"
    echo "pyproject $(sha256sum pyproject.toml | cut -d' ' -f1)"
    echo "bootstrap $(sha256sum scripts/bootstrap.sh | cut -d' ' -f1)"
    echo "suitesparse $(have_suitesparse && echo yes || echo no)"
    echo "openblas $(have_openblas && echo yes || echo no)"
    echo "chromium $(have_chromium && echo yes || echo no)"
}

# -P: never put the checkout on sys.path, where types/ would shadow the standard library.
if [ -f "$STAMP" ] && [ "$(stamp)" = "$(cat "$STAMP")" ] \
        && "$VENV/bin/python" -P -c "import graphopt" 2>/dev/null; then
    cholmod=$("$VENV/bin/python" -P -c "from graphopt.solvers import CHOLMOD_AVAILABLE as a, \
cholmod_blas as b; print(('with CHOLMOD on ' + (b().split('/')[-2] or 'BLAS')) if a else 'without CHOLMOD')")
    say "$VENV is up to date ($cholmod); nothing to do"
    exit 0
fi

# Run a step quietly, appending its output to the log; on failure show the log and stop.
run_logged() {
    local what=$1
    shift
    echo "### $what: $*" >>"$LOG"
    if ! "$@" >>"$LOG" 2>&1; then
        echo "bootstrap: $what failed; the output follows (also in $LOG):" >&2
        cat "$LOG" >&2
        exit 1
    fi
}

start=$SECONDS
rm -f "$STAMP"  # written again only after a complete set-up
packages=""
have_suitesparse || packages="libsuitesparse-dev"
have_openblas || packages="$packages libopenblas0-pthread"
have_chromium || packages="$packages chromium"
packages=${packages# }
if [ -n "$packages" ] && command -v apt-get >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" = 0 ] || { command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null && sudo="sudo"; }
    if [ "$(id -u)" = 0 ] || [ -n "$sudo" ]; then
        say "installing $packages (CHOLMOD, an optimised BLAS for it, the browser test's Chromium)"
        ($sudo apt-get update -qq && $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $packages >/dev/null) \
            || say "could not install $packages; graphopt falls back to another linear solver or a slower BLAS, the browser test skips"
    else
        say "$packages missing and cannot be installed without root; CHOLMOD may be unavailable or slower, the browser test skips"
    fi
fi

if [ ! -x "$VENV/bin/python" ]; then
    say "creating $VENV ($("$PY" --version 2>&1))"
    "$PY" -P -m venv "$VENV"
    : >"$LOG"
    run_logged "upgrading pip" "$VENV/bin/python" -P -m pip install --upgrade pip
else
    : >"$LOG"
fi
say "installing graphopt (editable) with its test tools into $VENV"
run_logged "installing graphopt" "$VENV/bin/python" -P -m pip install -e ".[test,browser]"
if have_suitesparse; then
    say "installing scikit-sparse for CHOLMOD (its first build compiles)"
    echo "### installing scikit-sparse" >>"$LOG"
    if ! "$VENV/bin/python" -P -m pip install "scikit-sparse>=0.4.16,<0.5" >>"$LOG" 2>&1; then
        tail -n 20 "$LOG" >&2
        say "scikit-sparse failed to build (above; all in $LOG); graphopt will use another linear solver"
    fi
fi
# Deprecations would otherwise go unnoticed in the log (pip's notes about the local package
# index locations that do not hold a package are expected and left there).
grep -i "deprecat" "$LOG" | sed 's/^ */bootstrap: warning: /' || true
stamp >"$STAMP"
say "done in $((SECONDS - start)) s (pip's output: $LOG)"
