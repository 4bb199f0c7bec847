#!/usr/bin/env bash
# Build the image with podman where no Docker engine and no registry are at hand (CI, this repo's
# tests): a Debian base made with debootstrap, the CPU torch wheel from a local folder. Docker
# format, since OCI images drop HEALTHCHECK.
#   docker/build-local.sh [TAG]      env: WHEELS (folder with a torch wheel, default /opt/wheels),
#                                         TORCH_SPEC (default torch==2.13.0+cpu)
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
tag=${1:-localhost/inhand-tracker:dev}
work=${PODMAN_WORK:-$HOME/.cache/inhand-tracker/podman}
mkdir -p "$work"
export CONTAINERS_CONF=$work/containers.conf
cat > "$CONTAINERS_CONF" <<CONF
[containers]
default_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]
[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
events_logger = "file"
CONF
if ! podman image exists localhost/debian-base:bookworm; then
  echo "making the Debian base image with debootstrap ..."
  rm -rf "$work/rootfs"
  debootstrap --variant=minbase bookworm "$work/rootfs" http://deb.debian.org/debian > "$work/debootstrap.log"
  tar -C "$work/rootfs" -c . | podman import - localhost/debian-base:bookworm > /dev/null
  rm -rf "$work/rootfs"
fi
ca=/etc/ssl/certs/ca-certificates.crt
start=$(date +%s)
podman build --format docker -f "$root/docker/Dockerfile" -t "$tag" \
  --build-arg BASE=localhost/debian-base:bookworm \
  --build-arg TORCH_SPEC="${TORCH_SPEC:-torch==2.13.0+cpu}" \
  --build-arg PIP_FIND_LINKS=/wheels \
  -v "${WHEELS:-/opt/wheels}:/wheels:ro" \
  $( [ -f "$ca" ] && echo --secret "id=hostca,src=$ca" ) \
  "$root"
echo "build time: $(( $(date +%s) - start )) s"
echo "image size: $(podman image inspect "$tag" --format '{{.Size}}' | awk '{printf "%.0f MB", $1/1e6}')"
