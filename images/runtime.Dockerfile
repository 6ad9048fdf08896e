# cosim5g/runtime: one image for every federate (physics, camera, edge, robot, netsim, loops)
# and for the coordinator. Built by images/build.sh with the host wheelhouse as build context
# (deps/: dependency wheels + requirements.txt, project/: the cosim5g wheel); the build never
# reaches PyPI, only the Debian mirror for apt. No torch: inference uses ONNX Runtime.
ARG BASE_IMAGE=cosim5g/base:bookworm

# ---- os: interpreter, headless GL, init, unprivileged user ----------------------------------
FROM ${BASE_IMAGE} AS os
ENV DEBIAN_FRONTEND=noninteractive
# python3-venv: the venv below (and `python -m venv` for users). Headless MuJoCo rendering:
#   MUJOCO_GL=egl    -> libegl1 (glvnd loader) + libegl-mesa0 (Mesa's EGL vendor, software
#                       llvmpipe without a GPU) + libgl1-mesa-dri (the llvmpipe driver) + libgl1
#                       + libopengl0 (glvnd's libOpenGL, which PyOpenGL's EGL platform loads first)
#   MUJOCO_GL=osmesa -> libosmesa6 (fallback where EGL cannot start)
# tini: PID 1 that forwards SIGTERM and reaps children, so `docker stop` is a clean shutdown.
# The dpkg filter keeps docs (except copyright), man pages and translations out of the image.
RUN printf '%s\n' 'path-exclude=/usr/share/doc/*' 'path-include=/usr/share/doc/*/copyright' \
      'path-exclude=/usr/share/man/*' 'path-exclude=/usr/share/locale/*' \
      >/etc/dpkg/dpkg.cfg.d/cosim5g-slim \
 && apt-get update \
 && apt-get install -y --no-install-recommends \
      python3 python3-venv \
      libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libopengl0 libosmesa6 \
      ca-certificates tini \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb
# A fixed uid so run directories on the host can be made writable for it (see docs/docker.md).
RUN groupadd --system --gid 10001 cosim \
 && useradd --system --uid 10001 --gid cosim --home-dir /home/cosim --create-home \
      --shell /usr/sbin/nologin cosim

# ---- deps: the third-party venv, built in its own stage so the wheels (~300 MB of zip files)
# never become a layer of the final image --------------------------------------------------
FROM os AS deps
LABEL cosim5g.image="runtime-deps"
COPY deps/ /wheelhouse/deps/
RUN python3 -m venv /opt/venv \
 && /opt/venv/bin/pip install --no-cache-dir --no-index --find-links /wheelhouse/deps \
      -r /wheelhouse/deps/requirements.txt \
 && rm -rf /opt/venv/lib/python3.11/site-packages/pyarrow/tests \
           /opt/venv/lib/python3.11/site-packages/pyarrow/include \
 && if /opt/venv/bin/pip list 2>/dev/null | grep -qi '^torch '; then \
      echo "torch must not be in the runtime image" >&2; exit 1; fi

# ---- final ------------------------------------------------------------------------------------
FROM os
LABEL org.opencontainers.image.title="cosim5g runtime" \
      org.opencontainers.image.vendor="cosim5g" \
      org.opencontainers.image.description="cosim5g federates and coordinator (python -m services.main / cosim5g)" \
      cosim5g.image="runtime"
COPY --from=deps /opt/venv /opt/venv
# Containers run with a read-only root: nothing may need to write outside /tmp (a tmpfs) and
# the bind-mounted run directory. Byte code is compiled at install time; caches go to /tmp.
ENV PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    HOME=/tmp \
    XDG_CACHE_HOME=/tmp/.cache \
    MUJOCO_GL=egl \
    PYOPENGL_PLATFORM=egl
WORKDIR /tmp
ENTRYPOINT ["/usr/bin/tini", "--"]
CMD ["python", "-m", "services.main", "--help"]
# The NR cell compiled on the host, where it was built (make native): fabric.native uses it only
# while it matches the installed sources and loads here; the build log says which it is.
COPY native/ /opt/cosim5g-native/
ENV COSIM5G_NATIVE_DIR=/opt/cosim5g-native
# The project itself last: a source change rebuilds only these small steps.
COPY project/ /wheelhouse/project/
RUN pip install --no-cache-dir --no-index --no-deps /wheelhouse/project/*.whl \
 && rm -rf /wheelhouse \
 && python -c "import interfaces.api, services, netsim, experiments" \
 && python -c "from fabric.native import main; raise SystemExit(main(['status']))"
USER cosim:cosim
