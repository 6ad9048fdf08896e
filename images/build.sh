#!/usr/bin/env bash
# Build the cosim5g images without any container registry (docs/architecture.md sec. 8).
#
#   1. base image cosim5g/base:bookworm: local cache, else `docker pull debian:bookworm-slim`,
#      else debootstrap (minbase) + `docker import`, the rootfs tarball cached for the next build;
#   2. wheelhouse on the host: the runtime dependencies of pyproject.toml ([project].dependencies
#      plus the `api` and `plots` extras -- the coordinator draws sweeps' figures; never torch)
#      downloaded with pip, plus a wheel of the project;
#   3. cosim5g/runtime:latest (every federate and the coordinator) and cosim5g/prometheus:latest.
#
# Idempotent: a second run reuses the base image, the wheelhouse (until pyproject.toml changes)
# and docker's layer cache. Environment knobs:
#   COSIM5G_CACHE_DIR      where tarballs and wheels are kept (default: <repo>/.cache)
#   COSIM5G_DEBIAN_MIRROR  mirror URL for debootstrap (default: debootstrap's own default)
#   COSIM5G_PULL_TIMEOUT_S how long to try `docker pull` (default 30)
#   COSIM5G_REFRESH_WHEELS=1  re-resolve the dependency wheels even if pyproject.toml is unchanged
#   PYTHON                 the host interpreter used for pip (default python3; must be 3.11)
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="${COSIM5G_CACHE_DIR:-$REPO/.cache}"
IMAGES_DIR="$REPO/images"
BASE_IMAGE="cosim5g/base:bookworm"
RUNTIME_IMAGE="cosim5g/runtime:latest"
DEPS_IMAGE="cosim5g/runtime-deps:cache"
PROM_IMAGE="cosim5g/prometheus:latest"
PYTHON="${PYTHON:-python3}"
PULL_TIMEOUT_S="${COSIM5G_PULL_TIMEOUT_S:-30}"
# The images run Debian bookworm's python3 (3.11): wheels must be cp311 and manylinux tags
# whose glibc is <= bookworm's 2.36, whatever the host distribution is.
PY_VERSION="3.11"
GLIBC_MINOR_MAX=36

log() { printf '[images/build.sh] %s\n' "$*" >&2; }
die() { printf '[images/build.sh] ERROR: %s\n' "$*" >&2; exit 1; }
run() { log "+ $*"; "$@"; }

have_image() { docker image inspect "$1" >/dev/null 2>&1; }

# --------------------------------------------------------------------------------------------
# 0. Preconditions
# --------------------------------------------------------------------------------------------
command -v docker >/dev/null || die "docker CLI not found"
docker version --format '{{.Server.Version}}' >/dev/null 2>&1 \
  || die "Docker daemon not reachable (is it running, and may $(id -un) use it?)"
"$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || die "$PYTHON is $("$PYTHON" -V 2>&1); need Python 3.11 to fetch wheels matching the image's python3"
# A build run with sudo leaves the cache to the user who asked for it; one run as root before
# (without sudo) may have left it root's: say how to take it back rather than fail half-way.
if [[ "$(id -u)" == 0 && -n "${SUDO_UID:-}" ]]; then
  trap 'chown -R "$SUDO_UID:${SUDO_GID:-$SUDO_UID}" "$CACHE" 2>/dev/null || true' EXIT
fi
for d in "$CACHE" "$CACHE/images" "$CACHE/wheelhouse" "$CACHE/wheelhouse"/*/; do
  [[ ! -e "$d" || -w "$d" ]] \
    || die "$d is not writable by $(id -un) (a build as root left it so): sudo chown -R $(id -u):$(id -g) $CACHE"
done
mkdir -p "$CACHE/images" "$CACHE/wheelhouse"

# --------------------------------------------------------------------------------------------
# 1. Base image
# --------------------------------------------------------------------------------------------
# Keep the host's Debian apt sources (with -updates and -security) if the host is bookworm:
# debootstrap only writes the main suite. Nothing names a mirror host here.
host_bookworm_sources() {
  local f
  for f in /etc/apt/sources.list.d/debian.sources /etc/apt/sources.list; do
    if [[ -s "$f" ]] && grep -qE '^[^#]*bookworm' "$f"; then
      echo "$f"
      return 0
    fi
  done
  return 1
}

bootstrap_base() {
  local tarball="$CACHE/images/debian-bookworm-minbase.tar"
  if [[ -s "$tarball" ]]; then
    log "base: reusing cached debootstrap rootfs $tarball"
  else
    [[ "$(id -u)" == 0 ]] || die "no base image is cached and no registry answers: the base is bootstrapped with debootstrap, which needs root; run once: sudo PYTHON=$PYTHON bash images/build.sh"
    # Installs debootstrap when missing (as root, with apt), or says how and stops.
    bash "$IMAGES_DIR/host_setup.sh" debootstrap || die "debootstrap is needed to build the base image (see above)"
    local rootfs="$CACHE/images/rootfs.tmp"
    rm -rf "$rootfs"
    local mirror=()
    if [[ -n "${COSIM5G_DEBIAN_MIRROR:-}" ]]; then mirror=("$COSIM5G_DEBIAN_MIRROR"); fi
    log "base: debootstrap --variant=minbase bookworm (about 30 s)"
    run debootstrap --variant=minbase bookworm "$rootfs" "${mirror[@]}" \
      >"$CACHE/images/debootstrap.log" 2>&1 \
      || die "debootstrap failed: see $CACHE/images/debootstrap.log"
    local src
    if src="$(host_bookworm_sources)"; then
      log "base: apt sources taken from the host's $src"
      rm -f "$rootfs/etc/apt/sources.list"
      if [[ "$src" == *.sources ]]; then
        cp "$src" "$rootfs/etc/apt/sources.list.d/debian.sources"
      else
        grep -E '^[^#]*bookworm' "$src" >"$rootfs/etc/apt/sources.list"
      fi
    fi
    # Images never keep package indexes or downloaded .debs.
    rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/archives/*.deb
    log "base: packing rootfs into $tarball"
    tar --numeric-owner -C "$rootfs" -cf "$tarball.tmp" .
    mv "$tarball.tmp" "$tarball"
    rm -rf "$rootfs"
  fi
  log "base: docker import -> $BASE_IMAGE"
  docker import \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["/bin/bash"]' \
    "$tarball" "$BASE_IMAGE" >/dev/null
}

if have_image "$BASE_IMAGE"; then
  log "base: $BASE_IMAGE already in the local cache"
elif have_image debian:bookworm-slim; then
  log "base: tagging cached debian:bookworm-slim as $BASE_IMAGE"
  docker tag debian:bookworm-slim "$BASE_IMAGE"
elif log "base: trying docker pull debian:bookworm-slim (timeout ${PULL_TIMEOUT_S}s)" \
     && timeout "$PULL_TIMEOUT_S" docker pull -q debian:bookworm-slim >/dev/null 2>&1; then
  log "base: pulled; tagging as $BASE_IMAGE"
  docker tag debian:bookworm-slim "$BASE_IMAGE"
else
  log "base: no registry reachable; bootstrapping from Debian packages"
  bootstrap_base
fi

# --------------------------------------------------------------------------------------------
# 2. Wheelhouse (host side: no build step needs the network inside a container)
# --------------------------------------------------------------------------------------------
WH="$CACHE/wheelhouse"
REQS="$WH/requirements.txt"
"$PYTHON" - "$REPO/pyproject.toml" >"$REQS.tmp" <<'EOF'
"""Print the runtime requirements: [project].dependencies + the api and plots extras, no torch."""
import re
import sys
import tomllib

with open(sys.argv[1], "rb") as f:
    project = tomllib.load(f)["project"]
reqs = list(project.get("dependencies", []))
for extra in ("api", "plots"):
    reqs += project.get("optional-dependencies", {}).get(extra, [])
for r in sorted(set(reqs)):
    name = re.split(r"[\s<>=!~;\[]", r, maxsplit=1)[0].lower()
    if name.startswith("torch"):
        print(f"skipping {r}: torch is for training only, never in runtime images", file=sys.stderr)
        continue
    print(r)
EOF
mv "$REQS.tmp" "$REQS"

platform_args=(--only-binary=:all: --python-version "$PY_VERSION" --implementation cp --abi "cp${PY_VERSION/./}")
for minor in $(seq "$GLIBC_MINOR_MAX" -1 17); do
  platform_args+=(--platform "manylinux_2_${minor}_x86_64")
done
platform_args+=(--platform manylinux2014_x86_64 --platform linux_x86_64)

stamp="$(cat "$REQS" <(printf '%s\n' "${platform_args[@]}") | sha256sum | cut -c1-16)"
if [[ -f "$WH/deps/.stamp" && "$(cat "$WH/deps/.stamp")" == "$stamp" && "${COSIM5G_REFRESH_WHEELS:-0}" != 1 ]]; then
  wheels=("$WH/deps"/*.whl)
  log "wheelhouse: dependency wheels up to date (${#wheels[@]} wheels in $WH/deps)"
else
  log "wheelhouse: downloading dependency wheels for cp311/manylinux (glibc <= 2.$GLIBC_MINOR_MAX)"
  rm -rf "$WH/deps.new"
  mkdir -p "$WH/deps.new"
  reuse=()
  if [[ -d "$WH/deps" ]]; then reuse=(--find-links "$WH/deps"); fi  # reuse what we already have
  run "$PYTHON" -m pip download --quiet --dest "$WH/deps.new" "${platform_args[@]}" "${reuse[@]}" \
    -r "$REQS" || die "pip download of the runtime dependencies failed (is PyPI reachable?)"
  for whl in "$WH/deps.new"/*.whl; do
    case "${whl##*/}" in torch-*|torch_*|Torch*) die "torch leaked into the wheelhouse: $whl";; esac
  done
  cp "$REQS" "$WH/deps.new/requirements.txt"
  echo "$stamp" >"$WH/deps.new/.stamp"
  rm -rf "$WH/deps"
  mv "$WH/deps.new" "$WH/deps"
  wheels=("$WH/deps"/*.whl)
  log "wheelhouse: ${#wheels[@]} wheels, $(du -sh "$WH/deps" | cut -f1)"
fi

# The project wheel is built from a staged copy so setuptools never writes build/ or *.egg-info
# into the work tree; SOURCE_DATE_EPOCH makes the wheel byte-identical when the sources are, so
# docker's layer cache holds across builds.
log "wheelhouse: building the cosim5g wheel"
stage="$WH/src.stage"
rm -rf "$stage" "$WH/project.new"
mkdir -p "$stage" "$WH/project.new"
cp "$REPO/pyproject.toml" "$stage/"
# The packages pyproject.toml ships ([tool.setuptools.packages.find] include = ["coordinator*", ...]).
mapfile -t packages < <("$PYTHON" -c '
import sys, tomllib
find = tomllib.load(open(sys.argv[1], "rb"))["tool"]["setuptools"]["packages"]["find"]
print("\n".join(sorted({p.split(".")[0].rstrip("*") for p in find["include"]})))' "$REPO/pyproject.toml")
for pkg in "${packages[@]}"; do
  [[ -d "$REPO/$pkg" ]] && cp -r "$REPO/$pkg" "$stage/"
done
find "$stage" \( -name __pycache__ -o -name '*.pyc' \) -prune -exec rm -rf {} +
if [[ -f "$REPO/README.md" ]]; then
  cp "$REPO/README.md" "$stage/"
else
  log "wheelhouse: README.md missing in the repo; using a placeholder for the wheel metadata"
  echo "cosim5g" >"$stage/README.md"
fi
SOURCE_DATE_EPOCH=315532800 run "$PYTHON" -m pip wheel --quiet --no-deps --wheel-dir "$WH/project.new" "$stage" \
  || die "building the cosim5g wheel failed"
rm -rf "$stage"
if [[ -d "$WH/project" ]] && diff -rq "$WH/project" "$WH/project.new" >/dev/null; then
  rm -rf "$WH/project.new"  # unchanged: keep the old file (and its mtime) for docker's cache
else
  rm -rf "$WH/project"
  mv "$WH/project.new" "$WH/project"
fi
log "wheelhouse: $(ls "$WH/project")"

# The NR cell compiled on the host (make native, see fabric/native.py), for the image's
# /opt/cosim5g-native. The image uses it only while its stamp matches the sources it ships and it
# loads (same CPython minor, glibc no newer than bookworm's); otherwise netsim runs as pure Python.
native="$REPO/build/native/cpython-311"
rm -rf "$WH/native.new"
mkdir -p "$WH/native.new"
if [[ -f "$native/stamp.json" ]]; then
  cp -r "$native/." "$WH/native.new/"
  log "wheelhouse: compiled modules from ${native#"$REPO"/}"
else
  log "wheelhouse: no compiled modules in ${native#"$REPO"/} (make native): netsim runs as pure Python in the image"
fi
if [[ -d "$WH/native" ]] && diff -rq "$WH/native" "$WH/native.new" >/dev/null; then
  rm -rf "$WH/native.new"
else
  rm -rf "$WH/native"
  mv "$WH/native.new" "$WH/native"
fi

# --------------------------------------------------------------------------------------------
# 3. Images (the wheelhouse is the build context: nothing else is sent to the daemon)
# --------------------------------------------------------------------------------------------
build() {  # build <image> <dockerfile> [<context> [extra docker build args...]]
  local image="$1" dockerfile="$2" context="${3:-}"
  shift 3 || shift $#
  local blog="$CACHE/images/${image//[\/:]/_}.build.log"
  log "image: building $image from ${dockerfile#"$REPO"/} (log: $blog)"
  local rc=0
  if [[ -n "$context" ]]; then
    docker build --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$image" "$@" -f "$dockerfile" "$context" \
      >"$blog" 2>&1 || rc=$?
  else
    docker build --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$image" "$@" - <"$dockerfile" \
      >"$blog" 2>&1 || rc=$?
  fi
  if [[ $rc != 0 ]]; then
    tail -n 30 "$blog" >&2
    die "docker build of $image failed: full log in $blog"
  fi
}
# The deps stage gets a tag of its own: it is the layer cache that makes a warm build fast, and a
# name tells `docker images` readers what the 1 GB image is (nothing runs from it).
build "$DEPS_IMAGE" "$IMAGES_DIR/runtime.Dockerfile" "$WH" --target deps
build "$RUNTIME_IMAGE" "$IMAGES_DIR/runtime.Dockerfile" "$WH"
build "$PROM_IMAGE" "$IMAGES_DIR/prometheus.Dockerfile"

# A rebuild leaves the previous (now untagged) images of ours behind; drop them.
for kind in runtime runtime-deps prometheus; do
  mapfile -t stale < <(docker images -q --filter dangling=true --filter "label=cosim5g.image=$kind")
  if [[ ${#stale[@]} -gt 0 ]]; then
    log "cleanup: removing superseded $kind image(s) ${stale[*]}"
    docker rmi "${stale[@]}" >/dev/null 2>&1 || true
  fi
done

log "done:"
docker images --format '{{.Repository}}:{{.Tag}}  {{.Size}}' | grep '^cosim5g/' | sed 's/^/  /' >&2 || true
