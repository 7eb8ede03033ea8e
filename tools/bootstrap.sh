#!/usr/bin/env bash
# Set up fluxdrive from nothing, or check quickly that nothing needs doing.
#
#   1. .venv (repo root) created with Python 3.11 if missing;
#   2. requirements.lock installed exactly (packages no longer pinned are removed) and the
#      project installed editable (pip install -e .); skipped while the hash of
#      requirements.lock + pyproject.toml + this script's STAMP_VERSION is unchanged;
#   3. the ROS wheels' CMake export files repaired: they point at the wheel builder's
#      /opt/python/cpXY-cpXY include dirs; rewritten to this Python's and numpy's;
#   4. colcon build of src/ into .ws/{build,install,log} (merge install, symlink install),
#      skipped while the hash of the package manifests, build files, interface
#      definitions and resource markers is unchanged;
#   5. Debian's chromium package (the scope page's browser test drives it with playwright;
#      no browser build is ever downloaded) when missing: apt-get update + install as root;
#      not root / no apt-get / FLUXDRIVE_NO_BROWSER=1: a note, and the browser test skips;
#   6. the firmware's target toolchain (Debian's gcc-arm-none-eabi + libnewlib-arm-none-eabi
#      for the Cortex-M4F build, qemu-system-arm for its instruction count) when missing,
#      the same way (FLUXDRIVE_NO_ARM=1: a note, and those tests skip).
#   Steps 5 and 6 run only for what the command needs: FLUXDRIVE_BOOTSTRAP_EXTRAS lists them
#   ("browser", "arm"; the launcher sets it per command: `test` both, `bench` and `benchmark`
#   the toolchain, the demo neither); unset (this script run by hand), both.
#
# Needs only python3.11 (with headers), cmake and g++ on the machine; pip reaches the
# package index. Progress on stderr, prefixed "[bootstrap]". Exits non-zero on any failure.
# Safe to run concurrently: real work is serialised with flock on .ws/bootstrap.lock.
#
# Environment: FLUXDRIVE_PYTHON=/path/to/python3.11 to choose the interpreter;
# FLUXDRIVE_BOOTSTRAP_FORCE=1 to redo pip and colcon steps regardless of stamps.
set -euo pipefail

STAMP_VERSION=1 # bump to force every checkout to redo the pip step

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
WS="$ROOT/.ws"
PIP_STAMP="$VENV/.fluxdrive-pip.stamp"
COLCON_STAMP="$WS/.fluxdrive-colcon.stamp"
PKGS_STAMP="$WS/.fluxdrive-packages"

log() { echo "[bootstrap] $*" >&2; }
die() {
  echo "[bootstrap] ERROR: $*" >&2
  exit 1
}
show_log_and_die() { # $1 log file, $2 message
  if [ -f "$1" ]; then
    echo "[bootstrap] ---- last lines of $1 ----" >&2
    tail -n 40 "$1" >&2 || true
    echo "[bootstrap] ----" >&2
  fi
  die "$2 (full log: $1)"
}

# ---------------------------------------------------------------------------- stamps
pip_hash() {
  {
    echo "stamp-version $STAMP_VERSION"
    echo "venv $VENV"
    cat "$ROOT/requirements.lock" "$ROOT/pyproject.toml"
  } | sha256sum | cut -d' ' -f1
}

# Files whose change needs a colcon run. Python sources of ament_python packages are not
# among them: they are symlink-installed (develop mode), so edits show up without a build.
colcon_inputs() {
  (cd "$ROOT" && find src \
    \( -name build -o -name install -o -name log -o -name '__pycache__' -o -name '.*' \) -prune -o \
    -type f \( -name package.xml -o -name CMakeLists.txt -o -name setup.py -o -name setup.cfg \
    -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -name '*.cmake' -o -name COLCON_IGNORE \
    -o -path '*/resource/*' -o -path '*/launch/*.launch.py' \) -print | LC_ALL=C sort)
}
# config/ is installed into share/fluxdrive_bringup (its setup.py): a file added or removed
# there needs a colcon run (the files themselves are symlinked: edits show up without one)
config_names() { (cd "$ROOT" && find config -type f | LC_ALL=C sort); }
colcon_hash() {
  {
    echo "pip $(cat "$PIP_STAMP" 2>/dev/null || true)"
    config_names
    local f
    while IFS= read -r f; do
      echo "== $f"
      cat "$ROOT/$f"
    done < <(colcon_inputs)
  } | sha256sum | cut -d' ' -f1
}
package_list() { (cd "$ROOT" && find src -name package.xml -not -path '*/.*' | LC_ALL=C sort); }
# Interfaces built before whose source is gone (a removed .msg/.srv/.action; a dangling
# symlink in the symlink install): the merged install and the package's build tree keep their
# generated code, and the package's type support then fails to import (undefined symbol of
# the removed type).
stale_interfaces() {
  [ -d "$WS/install/share" ] || return 0
  local xml pkg f
  for xml in $(package_list); do
    pkg="$(basename "$(dirname "$xml")")"
    for f in "$WS/install/share/$pkg"/{msg/*.msg,srv/*.srv,action/*.action}; do
      { [ -e "$f" ] || [ -L "$f" ]; } && [ ! -e "$ROOT/$(dirname "$xml")/${f#"$WS/install/share/$pkg/"}" ] &&
        echo "$pkg/${f#"$WS/install/share/$pkg/"}"
    done
  done
  return 0
}

pip_current() { [ -x "$VENV/bin/python" ] && [ -f "$PIP_STAMP" ] && [ "$(cat "$PIP_STAMP")" = "$(pip_hash)" ]; }
# venvs and CMake build trees hold absolute paths: a moved checkout must start afresh.
moved() { [ -f "$VENV/.fluxdrive-root" ] && [ "$(cat "$VENV/.fluxdrive-root")" != "$ROOT" ]; }
colcon_current() {
  [ -f "$WS/install/local_setup.bash" ] && [ -f "$COLCON_STAMP" ] &&
    [ "$(cat "$COLCON_STAMP")" = "$(colcon_hash)" ]
}

# A browser for the scope page's test: Debian's chromium, or a note that it cannot be had.
BROWSER_NOTE="$WS/.fluxdrive-no-browser"
browser_done() { command -v chromium >/dev/null 2>&1 || [ -f "$BROWSER_NOTE" ]; }

# The firmware's Cortex-M4F cross toolchain and emulator, or a note that they cannot be had.
ARM_NOTE="$WS/.fluxdrive-no-arm"
ARM_PKGS="gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
arm_present() {
  command -v arm-none-eabi-gcc >/dev/null 2>&1 && command -v qemu-system-arm >/dev/null 2>&1 &&
    [ -d /usr/lib/arm-none-eabi/newlib ]
}
arm_done() { arm_present || [ -f "$ARM_NOTE" ]; }

# What this command needs beyond the venv and the workspace (see the header).
EXTRAS="${FLUXDRIVE_BOOTSTRAP_EXTRAS-browser arm}"
wants() { case " $EXTRAS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }

# ------------------------------------------------------------------------- fast path
if [ "${FLUXDRIVE_BOOTSTRAP_FORCE:-0}" != 1 ] && ! moved && pip_current && colcon_current &&
  { ! wants browser || browser_done; } && { ! wants arm || arm_done; }; then
  exit 0
fi

mkdir -p "$WS"
exec 9>"$WS/bootstrap.lock"
if ! flock -n 9; then
  log "another bootstrap is running; waiting for it..."
  flock 9
fi

# ----------------------------------------------------------------------- tool checks
for tool in cmake g++ make sha256sum; do
  command -v "$tool" >/dev/null 2>&1 || die "'$tool' not found on PATH; install it (Debian: apt-get install cmake g++ make)"
done
[ -f "$ROOT/requirements.lock" ] || die "requirements.lock missing at $ROOT"

# ----------------------------------------------------------------------------- venv
if moved; then
  log "checkout moved from $(cat "$VENV/.fluxdrive-root"): removing .venv and .ws/build, .ws/install"
  rm -rf "$VENV" "$WS/build" "$WS/install" "$COLCON_STAMP" "$PKGS_STAMP"
fi
if [ ! -x "$VENV/bin/python" ]; then
  PY="${FLUXDRIVE_PYTHON:-}"
  if [ -z "$PY" ]; then
    for cand in python3.11 python3 "${HOME:-/root}"/.pyenv/versions/3.11*/bin/python3.11 \
      /usr/local/bin/python3.11 /usr/bin/python3.11; do
      if command -v "$cand" >/dev/null 2>&1 &&
        [ "$("$cand" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)" = 3.11 ]; then
        PY="$(command -v "$cand")"
        break
      fi
    done
  fi
  [ -n "$PY" ] || die "Python 3.11 not found (requirements.lock is resolved for 3.11); set FLUXDRIVE_PYTHON"
  log "creating venv at .venv with $PY..."
  rm -rf "$VENV"
  "$PY" -m venv "$VENV" || die "python -m venv failed"
  echo "$ROOT" >"$VENV/.fluxdrive-root"
  rm -f "$PIP_STAMP"
fi
VPY="$VENV/bin/python"
[ "$("$VPY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')" = 3.11 ] ||
  die ".venv is not Python 3.11; remove .venv and run again"

PYINC="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
[ -f "$PYINC/Python.h" ] || die "Python headers missing ($PYINC/Python.h); install the -dev package of python3.11"

# ------------------------------------------------------------------------------ pip
if [ "${FLUXDRIVE_BOOTSTRAP_FORCE:-0}" = 1 ] || ! pip_current; then
  PIPLOG="$WS/pip.log"
  : >"$PIPLOG"
  # _ROS_WHEELS_BOOTSTRAP_COMPLETE=1: skip the wheels' re-exec of every python start
  # (see tools/env.sh); nothing here loads ROS libraries.
  export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
  PIP=("$VPY" -m pip --disable-pip-version-check --no-input)
  log "installing requirements.lock into .venv (log: .ws/pip.log)..."
  "${PIP[@]}" install -r "$ROOT/requirements.lock" >>"$PIPLOG" 2>&1 ||
    show_log_and_die "$PIPLOG" "pip install -r requirements.lock failed"

  # Remove what pip installed earlier but the lock no longer pins (keeps the venv exact).
  STALE="$("$VPY" "$ROOT/tools/freeze_lock.py" --stale "$ROOT/requirements.lock")" || die "could not compare the venv with requirements.lock"
  if [ -n "$STALE" ]; then
    log "removing packages no longer in requirements.lock: $(echo $STALE)"
    # shellcheck disable=SC2086
    "${PIP[@]}" uninstall -y $STALE >>"$PIPLOG" 2>&1 || show_log_and_die "$PIPLOG" "pip uninstall failed"
  fi

  log "installing the project (editable)..."
  "${PIP[@]}" install --no-deps --no-build-isolation -e "$ROOT" >>"$PIPLOG" 2>&1 ||
    show_log_and_die "$PIPLOG" "pip install -e . failed"

  # The ROS wheels' CMake export files name the wheel builder's interpreter
  # (/opt/python/cp311-cp311/include/python3.11 and .../site-packages/numpy/_core/include).
  # Point them at this venv's Python include dir and numpy include dir.
  NPINC="$("$VPY" -c 'import numpy; print(numpy.get_include())')" || die "numpy not importable in .venv"
  log "repairing CMake export files of the ROS wheels (python: $PYINC, numpy: $NPINC)..."
  BUILDER_RE='/opt/python/cp[0-9]+-cp[0-9]+t?'
  mapfile -t CMAKE_FILES < <(grep -rlIE --include='*.cmake' "$BUILDER_RE" "$VENV" 2>/dev/null || true)
  if [ "${#CMAKE_FILES[@]}" -gt 0 ]; then
    sed -i -E \
      -e "s#${BUILDER_RE}/lib/python3\.[0-9]+t?/site-packages/numpy/(_core|core)/include#${NPINC}#g" \
      -e "s#${BUILDER_RE}/include/python3\.[0-9]+t?#${PYINC}#g" \
      "${CMAKE_FILES[@]}" || die "sed on CMake export files failed"
  fi
  LEFT="$(grep -rlIE --include='*.cmake' "$BUILDER_RE" "$VENV" 2>/dev/null || true)"
  [ -z "$LEFT" ] || die "CMake files still name the wheel builder's paths: $LEFT"
  log "repaired ${#CMAKE_FILES[@]} CMake export files"

  # Sanity: the ROS client library loads with its rmw (in a child with the wheels' own
  # bootstrapper, i.e. without the guard variable).
  (unset _ROS_WHEELS_BOOTSTRAP_COMPLETE && "$VPY" -c 'import rclpy, numpy, numba, rosbags') >>"$PIPLOG" 2>&1 ||
    show_log_and_die "$PIPLOG" "import check (rclpy, numpy, numba, rosbags) failed in .venv"

  pip_hash >"$PIP_STAMP"
  rm -f "$COLCON_STAMP" # a changed venv means the workspace must be rebuilt against it
  log "venv ready"
fi

# --------------------------------------------------------------------------- colcon
if [ "${FLUXDRIVE_BOOTSTRAP_FORCE:-0}" = 1 ] || ! colcon_current; then
  # A package removed or moved: start clean, a merged install keeps its files otherwise.
  if [ -f "$PKGS_STAMP" ] && [ -n "$(LC_ALL=C comm -23 "$PKGS_STAMP" <(package_list))" ]; then
    log "packages gone from src/ ($(LC_ALL=C comm -23 "$PKGS_STAMP" <(package_list) | tr '\n' ' ')): removing .ws/build and .ws/install"
    rm -rf "$WS/build" "$WS/install"
  fi
  if [ -n "$(stale_interfaces)" ]; then
    log "interfaces gone from src/ ($(stale_interfaces | tr '\n' ' ')): removing .ws/build and .ws/install"
    rm -rf "$WS/build" "$WS/install"
  fi
  rm -f "$COLCON_STAMP" # an interrupted or failed build must not look current later
  CLOG="$WS/colcon-build.log"
  log "colcon build of src/ into .ws/ (log: .ws/colcon-build.log)..."
  t0=$SECONDS
  # Build against the venv only: drop whatever workspace the caller's shell has sourced.
  if ! env -u PYTHONPATH -u COLCON_PREFIX_PATH -u _ROS_WHEELS_BOOTSTRAP_COMPLETE \
    AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH" \
    COLCON_HOME="$WS/colcon_home" \
    "$VENV/bin/colcon" --log-base "$WS/log" build \
    --base-paths "$ROOT/src" \
    --build-base "$WS/build" --install-base "$WS/install" \
    --merge-install --symlink-install \
    --event-handlers console_direct+ console_cohesion- console_start_end- status- summary+ \
    --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
    -DCMAKE_BUILD_TYPE=Release \
    >"$CLOG" 2>&1; then
    show_log_and_die "$CLOG" "colcon build failed"
  fi
  [ -f "$WS/install/local_setup.bash" ] || show_log_and_die "$CLOG" "colcon produced no .ws/install/local_setup.bash"
  package_list >"$PKGS_STAMP"
  colcon_hash >"$COLCON_STAMP"
  log "workspace built in $((SECONDS - t0)) s"
fi

# -------------------------------------------------------------------------- browser
if wants browser && ! command -v chromium >/dev/null 2>&1 && [ ! -f "$BROWSER_NOTE" ]; then
  if [ "${FLUXDRIVE_NO_BROWSER:-0}" = 1 ]; then
    echo "FLUXDRIVE_NO_BROWSER=1" >"$BROWSER_NOTE"
    log "chromium not installed (FLUXDRIVE_NO_BROWSER=1): the scope's browser test will skip"
  elif [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    ALOG="$WS/apt-chromium.log"
    log "installing Debian's chromium for the scope's browser test (log: .ws/apt-chromium.log)..."
    if ! { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; } \
      >"$ALOG" 2>&1; then
      tail -n 5 "$ALOG" >&2 || true
      echo "apt-get failed" >"$BROWSER_NOTE"
      log "WARNING: apt-get install chromium failed (log: .ws/apt-chromium.log); the scope's browser test skips until it is installed (remove $BROWSER_NOTE to retry)"
    else
      log "chromium installed: $(command -v chromium)"
    fi
  else
    echo "not root or no apt-get" >"$BROWSER_NOTE"
    log "chromium missing and cannot be installed here (not root / no apt-get): install Debian's chromium package for the scope's browser test; it skips meanwhile"
  fi
fi

# ---------------------------------------------------------------- firmware toolchain
if wants arm && ! arm_present && [ ! -f "$ARM_NOTE" ]; then
  if [ "${FLUXDRIVE_NO_ARM:-0}" = 1 ]; then
    echo "FLUXDRIVE_NO_ARM=1" >"$ARM_NOTE"
    log "ARM toolchain not installed (FLUXDRIVE_NO_ARM=1): the firmware's target tests skip"
  elif [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    ALOG="$WS/apt-arm.log"
    log "installing Debian's $ARM_PKGS for the firmware target build (log: .ws/apt-arm.log)..."
    # shellcheck disable=SC2086
    if ! { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
      --no-install-recommends $ARM_PKGS; } >"$ALOG" 2>&1; then
      tail -n 5 "$ALOG" >&2 || true
      echo "apt-get failed" >"$ARM_NOTE"
      log "WARNING: apt-get install of the ARM toolchain failed (log: .ws/apt-arm.log); the firmware's target tests skip until it is installed (remove $ARM_NOTE to retry)"
    else
      log "ARM toolchain installed: $(command -v arm-none-eabi-gcc), $(command -v qemu-system-arm)"
    fi
  else
    echo "not root or no apt-get" >"$ARM_NOTE"
    log "ARM toolchain missing and cannot be installed here (not root / no apt-get): install Debian's $ARM_PKGS; the firmware's target tests skip meanwhile"
  fi
fi
