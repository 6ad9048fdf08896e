#!/usr/bin/env bash
# What cosim5g needs from the host, checked one by one (docs/architecture.md sec. 8, docs/docker.md).
#
#   bash images/host_setup.sh [--check] [python] [docker] [egl] [debootstrap]
#
# Without arguments: python, docker, egl. Whatever is missing is installed with apt-get when
# this runs as root on a Debian/Ubuntu host (one `apt-get update`, skipped when this script ran
# one less than an hour ago); otherwise, or with --check, the exact command to run is printed
# and the script exits 1 before anything long starts.
#
#   python       $PYTHON (default python3.11, else python3) is Python 3.11 and can make a venv
#   docker       the docker CLI, a daemon this user may use, and compose (`docker compose` or
#                `docker-compose`)
#   egl          EGL + Mesa (llvmpipe) for headless host-side renders (MUJOCO_GL=egl)
#   debootstrap  only asked for by images/build.sh, when no base image is cached and no
#                registry answers: the base is then bootstrapped from Debian packages
set -euo pipefail

if [[ -z "${PYTHON:-}" ]]; then
  if command -v python3.11 >/dev/null; then PYTHON=python3.11; else PYTHON=python3; fi
fi

log() { printf '[host_setup] %s\n' "$*" >&2; }
check_only=""

is_root() { [[ "$(id -u)" == 0 ]]; }
have_apt() { command -v apt-get >/dev/null && command -v dpkg >/dev/null; }
# apt keeps the server's dates on the lists it fetches, so their age says nothing about when the
# last update ran: a stamp of our own does.
APT_STAMP=/var/cache/apt/cosim5g-apt-update.stamp
apt_update_once() {
  if [[ -z "$(find "$APT_STAMP" -mmin -60 2>/dev/null)" ]]; then
    log "+ apt-get update"
    apt-get update -qq
    touch "$APT_STAMP"
  fi
}
may_install() { is_root && have_apt && [[ -z "$check_only${COSIM5G_HOST_SETUP_RECHECK:-}" ]]; }
# A package the host's apt sources know (a candidate version exists). A machine whose package
# lists were never fetched knows none: as root, fetch them first.
apt_has() {
  if may_install && ! compgen -G '/var/lib/apt/lists/*Packages*' >/dev/null; then apt_update_once; fi
  [[ "$(apt-cache policy "$1" 2>/dev/null | awk '/Candidate:/ {print $2}')" =~ ^[0-9] ]]
}

apt_pkgs=()     # packages that fix what is missing
manual=()       # what apt cannot fix: printed as is

need_pkg() {  # need_pkg <why> <package>...
  local why="$1"
  shift
  log "missing: $why"
  apt_pkgs+=("$@")
}

need_manual() {
  log "missing: $1"
  manual+=("$2")
}

# ---- python ------------------------------------------------------------------------------------
check_python() {
  # The Makefile prefers python3.11 when it exists, as here: an older or newer python3 is fine
  # beside it.
  if [[ "$PYTHON" == python3 ]] && command -v python3.11 >/dev/null \
     && ! python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    PYTHON=python3.11
  fi
  if ! command -v "$PYTHON" >/dev/null; then
    need_python "$PYTHON not found"
    return
  fi
  if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    need_python "$PYTHON is $("$PYTHON" -V 2>&1 | head -n 1), the project needs Python 3.11"
    return
  fi
  if ! "$PYTHON" -c 'import ensurepip, venv' 2>/dev/null; then
    local exe
    exe="$(readlink -f "$(command -v "$PYTHON")")"
    if have_apt && dpkg -S "$exe" >/dev/null 2>&1; then
      need_pkg "$PYTHON cannot make a venv (no ensurepip)" python3.11-venv
    else
      need_manual "$PYTHON ($exe) cannot make a venv (no ensurepip)" \
        "reinstall $exe with its venv/ensurepip module, or run make with PYTHON=<a Python 3.11 that has it>"
    fi
  fi
}

need_python() {
  if command -v python3.11 >/dev/null && python3.11 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    need_manual "$1" "run make with PYTHON=python3.11"
  elif have_apt && apt_has python3.11; then
    need_pkg "$1" python3.11 python3.11-venv
    PYTHON=python3.11
  else
    need_manual "$1" \
      "install Python 3.11 (this distribution has no python3.11 package), then run make with PYTHON=/path/to/python3.11"
  fi
}

# ---- docker ------------------------------------------------------------------------------------
check_docker() {
  if ! command -v docker >/dev/null; then
    need_pkg "the docker CLI and daemon" docker.io
  elif ! docker version --format '{{.Server.Version}}' >/dev/null 2>&1; then
    if [[ -S /var/run/docker.sock && ! -w /var/run/docker.sock ]] && ! is_root; then
      need_manual "the Docker daemon does not let $(id -un) in" \
        "sudo usermod -aG docker $(id -un)   # then log in again (or run make as root)"
    else
      need_manual "the Docker daemon is not running" "sudo systemctl start docker   # or: sudo service docker start"
    fi
  fi
  if ! docker compose version >/dev/null 2>&1 && ! command -v docker-compose >/dev/null; then
    local pkg=""
    if have_apt; then
      for p in docker-compose-plugin docker-compose-v2 docker-compose; do
        if apt_has "$p"; then pkg="$p"; break; fi
      done
    fi
    if [[ -n "$pkg" ]]; then
      need_pkg "docker compose (neither \`docker compose\` nor docker-compose)" "$pkg"
    else
      need_manual "docker compose (neither \`docker compose\` nor docker-compose)" \
        "install Docker Compose (the compose plugin, or docker-compose >= 1.29)"
    fi
  fi
}

# ---- egl ---------------------------------------------------------------------------------------
# libEGL.so.1 (glvnd loader) needs a vendor (Mesa's libEGL_mesa) and a driver (llvmpipe in the
# swrast DRI module) to render without a GPU; PyOpenGL's EGL platform loads libOpenGL.so.0 first.
check_egl() {
  local libs missing=()
  # ldconfig is in /sbin, which a user's PATH often lacks.
  libs="$({ command -v ldconfig >/dev/null && ldconfig -p || /sbin/ldconfig -p; } 2>/dev/null || true)"
  grep -q 'libEGL\.so\.1 ' <<<"$libs" || missing+=(libegl1)
  grep -q 'libEGL_mesa\.so\.0 ' <<<"$libs" || missing+=(libegl-mesa0)
  grep -q 'libOpenGL\.so\.0 ' <<<"$libs" || missing+=(libopengl0)
  compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null || compgen -G '/usr/lib/dri/swrast_dri.so' >/dev/null \
    || missing+=(libgl1-mesa-dri)
  if [[ ${#missing[@]} -gt 0 ]]; then
    need_pkg "EGL/Mesa libraries for headless renders (${missing[*]})" "${missing[@]}"
  fi
}

# ---- debootstrap -------------------------------------------------------------------------------
check_debootstrap() {
  command -v debootstrap >/dev/null || need_pkg "debootstrap (no base image cached, no registry)" debootstrap
}

# ---- main --------------------------------------------------------------------------------------
if [[ "${1:-}" == --check ]]; then check_only=1; shift; fi
parts=("$@")
[[ ${#parts[@]} -gt 0 ]] || parts=(python docker egl)
for part in "${parts[@]}"; do
  case "$part" in
    python) check_python ;;
    docker) check_docker ;;
    egl) check_egl ;;
    debootstrap) check_debootstrap ;;
    *) log "unknown check '$part': python, docker, egl or debootstrap"; exit 2 ;;
  esac
done

if [[ ${#apt_pkgs[@]} -eq 0 && ${#manual[@]} -eq 0 ]]; then
  log "ok: ${parts[*]}"
  exit 0
fi

if [[ ${#apt_pkgs[@]} -gt 0 ]] && may_install; then
  apt_update_once
  log "+ apt-get install -y --no-install-recommends ${apt_pkgs[*]}"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${apt_pkgs[@]}" >/dev/null
  apt_pkgs=()
fi

if [[ ${#apt_pkgs[@]} -gt 0 || ${#manual[@]} -gt 0 ]]; then
  log "the host is not ready; run:"
  if [[ ${#apt_pkgs[@]} -gt 0 ]]; then
    if ! have_apt; then
      log "  install the equivalent of the Debian packages: ${apt_pkgs[*]}"
    elif command -v sudo >/dev/null; then
      log "  sudo apt-get update && sudo apt-get install -y --no-install-recommends ${apt_pkgs[*]}"
    else
      log "  as root: apt-get update && apt-get install -y --no-install-recommends ${apt_pkgs[*]}"
    fi
  fi
  for m in "${manual[@]}"; do log "  $m"; done
  log "then run the same make command again"
  exit 1
fi

# What was installed must now be there (docker.io, for one, starts its daemon on install); a
# second pass that still misses something prints the command instead of installing again.
COSIM5G_HOST_SETUP_RECHECK=1 exec bash "$0" "${parts[@]}"
