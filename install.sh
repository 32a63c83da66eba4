#!/usr/bin/env bash
# Install elo-mitsuba and everything it needs, then run the main job or the tests.
#
#   bash install.sh          install, verify, render the shipped scene athene_flat
#                            into athene_flat.exr in the folder it was started from
#                            (ELO_OUT_DIR to choose another; never into the checkout unless
#                            started there)
#   bash install.sh --test   install, verify, run the test suite: python3 -m pytest -q tests
#                            (further arguments are passed on to pytest)
#
# What it installs:
#   * an LLVM that Mitsuba's llvm variants run with (Debian's libllvm19; Debian 12's default
#     LLVM 15/16 aborts them). Skipped when one is already present or DRJIT_LIBLLVM_PATH is set.
#     Uses apt-get (update + install), through sudo when not root.
#   * this package, editable, with its test and sweep extras, into the current python3:
#     python3 -m pip install -e '.[test,sweep]'
#
# Works unattended (CI=true, no stdin). Exits non-zero on any failure, including failing tests.
# Environment: PYTHON (default python3), ELO_SKIP_APT=1 to never touch apt.
set -euo pipefail

OUT_DIR=${ELO_OUT_DIR:-$PWD}  # where the main job's image goes: the caller's folder, not the checkout
cd "$(dirname "${BASH_SOURCE[0]}")"
PYTHON="${PYTHON:-python3}"

say() { printf '[install.sh] %s\n' "$*" >&2; }
die() { printf '[install.sh] error: %s\n' "$*" >&2; exit 1; }

MODE=run
if [[ "${1:-}" == "--test" ]]; then
    MODE=test
    shift
elif [[ "${1:-}" == "-h" || "${1:-}" == "--help" ]]; then
    sed -n '2,17p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
    exit 0
elif [[ $# -gt 0 ]]; then
    die "unknown argument '$1' (use --test, or nothing)"
fi

# --- 1. Python ----------------------------------------------------------------------------------
command -v "$PYTHON" >/dev/null 2>&1 || die "$PYTHON not found; install Python >= 3.11"
"$PYTHON" - <<'EOF' || die "elo-mitsuba needs Python >= 3.11 (found $("$PYTHON" --version 2>&1))"
import sys
sys.exit(0 if sys.version_info >= (3, 11) else 1)
EOF

# --- 2. LLVM >= 17 for Dr.Jit's llvm backend ---------------------------------------------------
have_good_llvm() {
    # A libLLVM of major version 17 or newer known to the dynamic loader.
    ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-(1[7-9]|[2-9][0-9])[.0-9]*\.so|\.so\.(1[7-9]|[2-9][0-9]))' && return 0
    compgen -G '/usr/lib/*/libLLVM-1[7-9]*.so*' >/dev/null 2>&1 && return 0
    compgen -G '/usr/lib/*/libLLVM.so.1[7-9]*' >/dev/null 2>&1 && return 0
    compgen -G '/usr/lib/llvm-1[7-9]/lib/libLLVM*.so*' >/dev/null 2>&1 && return 0
    return 1
}

as_root() {
    if [[ "$(id -u)" -eq 0 ]]; then
        "$@"
    elif command -v sudo >/dev/null 2>&1; then
        if [[ -n "${CI:-}" || ! -t 0 ]]; then
            sudo -n "$@"   # unattended: never wait for a password prompt
        else
            sudo "$@"
        fi
    else
        return 1
    fi
}

if [[ -n "${DRJIT_LIBLLVM_PATH:-}" ]]; then
    say "DRJIT_LIBLLVM_PATH=$DRJIT_LIBLLVM_PATH is set; not installing an LLVM"
elif [[ "${ELO_SKIP_APT:-0}" == 1 ]]; then
    say "ELO_SKIP_APT=1; not installing an LLVM"
elif have_good_llvm; then
    say "an LLVM >= 17 is present"
elif command -v apt-get >/dev/null 2>&1; then
    say "installing libllvm19 with apt-get (Debian 12's default LLVM aborts Mitsuba)"
    export DEBIAN_FRONTEND=noninteractive
    as_root apt-get update -q \
        || die "apt-get update failed (run as root, or with passwordless sudo)"
    installed=""
    for pkg in libllvm19 libllvm18 libllvm17; do
        if as_root apt-get install -y -q --no-install-recommends "$pkg" </dev/null; then
            installed=$pkg
            break
        fi
        say "$pkg is not installable here, trying an older one"
    done
    [[ -n "$installed" ]] \
        || die "could not install libllvm19/18/17; install an LLVM >= 17 and set DRJIT_LIBLLVM_PATH to its libLLVM.so"
    say "installed $installed"
else
    say "no apt-get here: install an LLVM >= 17 yourself and set DRJIT_LIBLLVM_PATH to its libLLVM.so"
fi

# --- 3. the package -----------------------------------------------------------------------------
if ! "$PYTHON" -m pip --version >/dev/null 2>&1; then
    say "pip is missing for $PYTHON; trying ensurepip"
    "$PYTHON" -m ensurepip --upgrade >/dev/null 2>&1 \
        || die "$PYTHON has no pip (on Debian: apt-get install python3-pip python3-venv)"
fi
PIP_ARGS=(install --disable-pip-version-check -q -e ".[test,sweep]")
pip_out=$(mktemp)
trap 'rm -f "$pip_out"' EXIT
say "pip install -e '.[test,sweep]' into $("$PYTHON" -c 'import sys; print(sys.executable)')"
if ! "$PYTHON" -m pip "${PIP_ARGS[@]}" 2>"$pip_out" </dev/null; then
    if grep -q externally-managed-environment "$pip_out"; then
        if [[ -n "${CI:-}" ]]; then
            say "$PYTHON is externally managed (PEP 668); CI=true, so installing with --break-system-packages"
            "$PYTHON" -m pip "${PIP_ARGS[@]}" --break-system-packages </dev/null \
                || die "pip install failed"
        else
            cat "$pip_out" >&2
            die "$PYTHON is managed by the system (PEP 668): activate a virtual environment first (python3 -m venv .venv && . .venv/bin/activate) and run bash install.sh again"
        fi
    else
        cat "$pip_out" >&2
        die "pip install -e '.[test,sweep]' failed"
    fi
fi

# --- 4. verify ----------------------------------------------------------------------------------
say "verifying: import elo_mitsuba; elo_mitsuba.ensure_variant()"
"$PYTHON" -c "import elo_mitsuba; mi = elo_mitsuba.ensure_variant(); print('[install.sh] elo-mitsuba', elo_mitsuba.__version__, 'on Mitsuba', mi.__version__, 'variant', mi.variant())" \
    || die "the installation does not work (see the line above)"

# --- 5. the job ---------------------------------------------------------------------------------
if [[ "$MODE" == test ]]; then
    say "running: $PYTHON -m pytest -q tests $*"
    exec "$PYTHON" -m pytest -q tests "$@"
fi

# The console script pip installed for $PYTHON; else one on PATH; else the module itself.
scripts_dir=$("$PYTHON" -c 'import sysconfig; print(sysconfig.get_path("scripts"))')
if [[ -x "$scripts_dir/elo-mitsuba" ]]; then
    ELO=("$scripts_dir/elo-mitsuba")
    command -v elo-mitsuba >/dev/null 2>&1 || say "note: add $scripts_dir to PATH to type elo-mitsuba"
elif command -v elo-mitsuba >/dev/null 2>&1; then
    ELO=(elo-mitsuba)
else
    ELO=("$PYTHON" -m elo_mitsuba)
fi
if "${ELO[@]}" render --help >/dev/null 2>&1; then
    say "running: elo-mitsuba render athene_flat -o $OUT_DIR/athene_flat.exr --overwrite"
    "${ELO[@]}" render athene_flat -o "$OUT_DIR/athene_flat.exr" --overwrite
    say "done: $OUT_DIR/athene_flat.exr"
else
    say "installed and verified; the renderer (elo-mitsuba render) is not part of this version yet"
fi
