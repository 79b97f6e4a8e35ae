# The agos image: every process of docs/DEPLOY.md (router, evaluator, world worker, agents, eval job,
# vlm-standin) is `agos <command>` in this image.
#
#   docker build -t agos:local .                      # the ordinary way: python:3.11-slim + PyPI
#
# The dependencies are exactly requirements.lock.txt (exported from uv.lock by `make lock`, every
# file checked by its hash); agos itself is then installed without dependencies. Without a reachable
# package index, build a wheelhouse on a host that has one and install from it:
#
#   pip wheel -w .wheels -r requirements.lock.txt && pip wheel -w .wheels "setuptools>=77" wheel
#   docker build --build-arg WHEELHOUSE=.wheels -t agos:local .
#   docker build --build-arg WHEELHOUSE=.wheels --build-arg BASE_IMAGE=agos-base:bookworm -t agos:local .
#
# BASE_IMAGE must have python3 (3.11 or newer, matching the wheels) with venv, pip and useradd
# (`make deploy-test` makes agos-base:bookworm by debootstrap). agos itself is always built from
# the context's source (so the wheelhouse needs the build backend too, and may be older than the
# source). It is used only in the build stage: the final image holds the virtual environment
# /opt/agos, the uv.lock it was installed from (/opt/agos/uv.lock: its sha256 goes into every run's
# and record's provenance, runtime/provenance.py) and no wheels.
#
# World workers that render with EGL ([world] renderer = "egl", on GPUs: docs/DEPLOY.md, "GPU world
# workers") need the EGL libraries, which the default image leaves out:
#
#   docker build --build-arg RENDERER=egl -t agos:egl .
#
# adds Debian's EGL loader (GLVND) and Mesa's EGL with its software driver (llvmpipe, where no GPU is
# given); on an NVIDIA GPU the container toolkit adds the driver's own EGL library at run time when
# the container asks for the `graphics` capability. Needs apt in BASE_IMAGE and a reachable mirror.

ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
ARG WHEELHOUSE=
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 PYTHONDONTWRITEBYTECODE=1
COPY . /src
RUN python3 -m venv /opt/agos \
 && if [ -n "$WHEELHOUSE" ]; then set -- --no-index --find-links "/src/$WHEELHOUSE"; fi \
 && /opt/agos/bin/pip install "$@" --require-hashes -r /src/requirements.lock.txt \
 && /opt/agos/bin/pip install "$@" --no-deps /src \
 && cp /src/uv.lock /opt/agos/uv.lock \
 && /opt/agos/bin/pip check \
 && /opt/agos/bin/agos --help > /dev/null

FROM ${BASE_IMAGE}
ARG RENDERER=
COPY --from=build /opt/agos /opt/agos
RUN if [ "$RENDERER" = egl ]; then \
        apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
            libegl1 libegl-mesa0 libgl1-mesa-dri && rm -rf /var/lib/apt/lists/*; \
    elif [ -n "$RENDERER" ]; then echo "RENDERER=$RENDERER: give egl, or nothing (TinyRenderer needs no library)" >&2; exit 1; \
    fi
# A fixed non-root user; compose may run as another uid (AGOS_UID, for bind-mounted run folders), so
# everything a process writes goes to /runs, /tmp or $HOME, all writable by any uid.
RUN useradd --uid 10001 --user-group --create-home --home-dir /home/agos --shell /usr/sbin/nologin agos \
 && mkdir -p /runs /assets /data \
 && chown agos:agos /runs /assets /data \
 && chmod 1777 /home/agos
ENV PATH=/opt/agos/bin:$PATH \
    HOME=/home/agos \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    AGOS_ASSET_CACHE=/tmp/agos-assets \
    AGOS_RUN__RUNS_DIR=/runs
USER agos
WORKDIR /home/agos
ENTRYPOINT ["agos"]
CMD ["--help"]
