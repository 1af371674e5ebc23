#!/usr/bin/env bash
# Set up everything lfrig needs, idempotently: a Python >= 3.12, the system library open3d needs,
# uv, and the locked environment in .venv/ (with the `lfrig` command in .venv/bin/).
#
#   ./setup.sh            set up (fast when everything is already there)
#   ./setup.sh --tests    also what the test suite needs: Debian's chromium and chromedriver (the
#                         report and preview pages are tested in a real headless browser)
#
# Environment:
#   LFRIG_PYTHON=/path/to/python3.12   use this interpreter instead of searching for one
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

FOR_TESTS=0
for arg in "$@"; do
  case "$arg" in
    --tests) FOR_TESTS=1 ;;
    *) printf 'setup: error: unknown option %s (use --tests or nothing)\n' "$arg" >&2; exit 2 ;;
  esac
done

say() { printf 'setup: %s\n' "$*" >&2; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

# --- a Python >= 3.12 --------------------------------------------------------------------------
is_py312() { "$1" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1; }

find_python() {
  if [ -n "${LFRIG_PYTHON:-}" ]; then
    is_py312 "$LFRIG_PYTHON" || die "LFRIG_PYTHON=$LFRIG_PYTHON is not a Python >= 3.12"
    echo "$LFRIG_PYTHON"; return
  fi
  local candidate
  for candidate in python3.12 python3.13 python3.14 python3 python; do
    if command -v "$candidate" >/dev/null 2>&1 && is_py312 "$(command -v "$candidate")"; then
      command -v "$candidate"; return
    fi
  done
  # pyenv may hold one that is not on PATH: ask pyenv where its versions live.
  if command -v pyenv >/dev/null 2>&1; then
    local root version
    root=$(pyenv root)
    for version in $(pyenv versions --bare 2>/dev/null | grep -E '^3\.(1[2-9]|[2-9][0-9])(\.[0-9]+)?$' | sort -V); do
      candidate="$root/versions/$version/bin/python3"
      if is_py312 "$candidate"; then echo "$candidate"; return; fi
    done
  fi
  return 1
}

PYTHON=$(find_python) || die "no Python >= 3.12 found (tried python3.12, python3.13, python3 on PATH and pyenv).
  Install one, e.g. 'pyenv install 3.12' or your system's python3.12 package, or set LFRIG_PYTHON."
say "Python: $PYTHON ($("$PYTHON" -c 'import sys; print(sys.version.split()[0])'))"

# --- the system library open3d needs -------------------------------------------------------------
if [ "$(uname -s)" = Linux ] && ! ldconfig -p 2>/dev/null | grep -q 'libusb-1\.0\.so\.0'; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    say "installing libusb-1.0-0 (open3d needs it) with apt-get"
    $SUDO apt-get update -qq >/dev/null && \
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null \
      || die "could not install libusb-1.0-0; install it by hand: sudo apt-get install libusb-1.0-0"
  else
    die "open3d needs libusb-1.0 (libusb-1.0.so.0); install it with your system's package manager"
  fi
fi

# --- Aravis (GenICam cameras, `--camera aravis:`) and what PyGObject builds against -------------
# PyGObject has no wheels: uv builds it from source against the system's GObject introspection
# (girepository 1.x here, hence pygobject<3.50) and cairo. The `aravis` extra holds it.
ARAVIS_PACKAGES="gir1.2-aravis-0.8 libaravis-0.8-0 libgirepository1.0-dev libcairo2-dev pkg-config"
SYNC_EXTRAS="--extra aravis"
if [ "$(uname -s)" = Linux ] && command -v dpkg-query >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  missing=""
  for package in $ARAVIS_PACKAGES; do
    dpkg-query -W -f='${db:Status-Abbrev}' "$package" 2>/dev/null | grep -q '^ii' || missing="$missing $package"
  done
  if [ -n "$missing" ]; then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    say "installing$missing (the Aravis camera driver and PyGObject's build needs) with apt-get"
    $SUDO apt-get update -qq >/dev/null && \
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null \
      || die "could not install$missing; install them by hand: sudo apt-get install$missing"
  fi
elif ! { command -v pkg-config >/dev/null 2>&1 && pkg-config --exists gobject-introspection-1.0 cairo aravis-0.8; }; then
  say "no apt-get, and Aravis/gobject-introspection/cairo not found by pkg-config: setting up without"
  say "the Aravis camera (--camera aravis:); install aravis, gobject-introspection and cairo to have it"
  SYNC_EXTRAS=""
fi

# --- a real browser for the tests (./test): Debian's chromium and its driver --------------------
# Nothing downloads a browser build: the tests drive /usr/bin/chromium through /usr/bin/chromedriver.
if [ "$FOR_TESTS" = 1 ] && [ "$(uname -s)" = Linux ] && command -v apt-get >/dev/null 2>&1 \
   && ! { command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; }; then
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  say "installing chromium chromium-driver (the tests open the report pages in a headless browser) with apt-get"
  $SUDO apt-get update -qq >/dev/null && \
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium chromium-driver >/dev/null \
    || die "could not install chromium chromium-driver; install them by hand: sudo apt-get install chromium chromium-driver"
fi

# --- uv ------------------------------------------------------------------------------------------
if command -v uv >/dev/null 2>&1; then
  UV=$(command -v uv)
else
  UV=.cache/uv-bootstrap/bin/uv
  if [ ! -x "$UV" ]; then
    say "installing uv into .cache/uv-bootstrap (from PyPI)"
    "$PYTHON" -m pip --version >/dev/null 2>&1 || "$PYTHON" -m ensurepip --upgrade >/dev/null 2>&1 \
      || die "$PYTHON has no pip; install uv (https://docs.astral.sh/uv/) or pip for it"
    PIP_ROOT_USER_ACTION=ignore "$PYTHON" -m pip install --quiet --disable-pip-version-check --target .cache/uv-bootstrap uv \
      || die "could not install uv with pip"
  fi
fi

# --- the locked environment ----------------------------------------------------------------------
export UV_PYTHON_DOWNLOADS=never
"$UV" sync --frozen $SYNC_EXTRAS --python "$PYTHON" --quiet || die "uv sync failed (see above)"
# uv installs no bytecode, and Python only writes it on import when PYTHONDONTWRITEBYTECODE is
# unset: without it every process compiles the ~500 modules numpy/numba/scipy import from source,
# ~1 s of CPU before any work (backgammon; docs/entropy-results.md, "Speed and memory"). Compile
# once here, lfrig's own packages too (installed in place, so not in purelib: the ~50 modules of
# `lfrig reconstruct`, most of them in the warm-up the estimate waits for); compileall skips files
# whose bytecode is current (~0.4 s when nothing changed), and a file edited since compiles on import
# as before.
.venv/bin/python -m compileall -qq "$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" \
  rig recon calib >/dev/null || say "warning: some modules did not compile to bytecode (imports are slower, nothing else)"
# numba compiles a kernel at its first call and caches it beside the sources (recon/**/__pycache__):
# without this, the first `lfrig reconstruct` on a machine compiles for ~70 s before and during its
# estimate. Every method's warm-up (recon.methods.warm_every_method: the entropy method's
# recon/entropy/preload.py, the baseline's sweep) compiles them here instead, once; with the cache
# current this takes ~1.4 s. The warm-ups and the loop below also build the C kernels with the
# system's cc (every library of recon.native.SIGNATURES: ~1 s each, once per source and CPU; a
# reconstruction then loads no numba; without a compiler their numba twins run instead).
say "compiling the estimators' kernels into numba's cache (a minute or two the first time)"
.venv/bin/python -c 'from recon.methods import warm_every_method; warm_every_method()' \
  || say "warning: the estimators' kernels did not compile here; the first reconstruction compiles them (slower, nothing else)"
.venv/bin/python -c 'from recon.native import SIGNATURES, library, unavailable
for name in SIGNATURES:
    if library(name) is None:
        print(f"recon/native/{name}.c was not built ({unavailable(name)}); its numba twins run instead: the same results, a slower start")' \
  | while read -r line; do say "note: $line"; done
say "environment ready: .venv/bin/lfrig"
