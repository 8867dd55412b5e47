# planarloc in a container that runs as a non-root user on a read-only install.
#
#   docker build -t planarloc .
#   docker run --rm -v "$PWD/data:/data:ro" planarloc localize --map /data/map.db /data/q.png \
#       --camera 'PINHOLE 640 480 500 500 320 240' --out -     # poses on stdout
#
# numba's compiled kernels are made here, at build time, as root (`planarloc warmup`), into the
# installed package's __pycache__ folders; the USER below cannot write there, and loads them
# read-only (planarloc.numerics.kernel_cache): the first pose comes in seconds, with or without a
# HOME. Caches planarloc may write later (evaluate's maps, a kernel not compiled here) go to that
# user's own folder in the temp folder, /tmp/planarloc-<uid> (mode 0700).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /src
COPY pyproject.toml README.md ./
COPY planarloc ./planarloc
RUN pip install . && rm -rf /src

# As root, before USER: compile every kernel into the (then read-only) install.
RUN planarloc warmup

# The user queries run as: no HOME, no write access to the install; /work is its working folder.
RUN useradd --system --uid 10001 --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin planarloc \
    && mkdir /work && chown planarloc /work
USER planarloc
WORKDIR /work

ENTRYPOINT ["planarloc"]
CMD ["--help"]
