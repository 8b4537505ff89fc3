#!/usr/bin/env bash
# The Docker lane without a Docker engine: a Debian 13 (trixie) root file system made by
# debootstrap (cached outside the repository), the repository bind-mounted at /app as the
# Dockerfile's COPY puts it, then docker/install.sh and the test suite run inside through chroot.
#   bash docker/rootfs_test.sh             set up, run scripts/run_tests.sh, exit with its code
#   bash docker/rootfs_test.sh CMD ARG...  set up, run CMD inside instead (e.g. bash for a shell)
# Env: BRAINMECH_ROOTFS (cache path), BRAINMECH_MIRROR (Debian mirror), PYTEST_ARGS (forwarded).
# Everything it mounts is unmounted on exit (success, failure, Ctrl-C, SIGTERM); mounts left by
# a SIGKILLed run are removed by the next run.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
ROOTFS=$(realpath -m "${BRAINMECH_ROOTFS:-/var/cache/brainmech/rootfs-trixie}")
MIRROR=${BRAINMECH_MIRROR:-http://deb.debian.org/debian}
SUITE=trixie

[ "$(id -u)" -eq 0 ] || { echo "rootfs_test: needs root (debootstrap, mount, chroot)" >&2; exit 1; }
# ruff and pytest walk the repository: a rootfs inside it would be scanned (and copied by docker build).
case "$ROOTFS/" in "$REPO"/*) echo "rootfs_test: BRAINMECH_ROOTFS must be outside $REPO" >&2; exit 1;; esac

# Mount points at or below $1 (as the kernel spells them), deepest first.
mounts_under() {
  local mp
  while read -r _ _ _ _ mp _; do
    mp=$(printf '%b' "$mp")  # mountinfo escapes spaces etc. as \040
    case $mp in "$1" | "$1"/*) echo "$mp" ;; esac
  done </proc/self/mountinfo | sort -r
}

# Unmount everything at or below $1; a lazy unmount when something still holds a mount busy.
unmount_under() {
  local mp mps
  for _ in 1 2 3; do  # a mount point may carry stacked mounts
    mapfile -t mps < <(mounts_under "$1")
    ((${#mps[@]})) || return 0
    for mp in "${mps[@]}"; do
      umount "$mp" 2>/dev/null || umount -l "$mp" 2>/dev/null || true
    done
  done
  if [ -n "$(mounts_under "$1")" ]; then
    echo "rootfs_test: could not unmount: $(mounts_under "$1" | tr '\n' ' ')" >&2
    return 1
  fi
}

BUILD_TMP=""
LOCKED=0
# shellcheck disable=SC2317  # run by the EXIT trap
cleanup() {
  local rc=$?
  trap - EXIT INT TERM HUP
  # Only the lock holder's mounts are ours: a run still waiting for the lock touches nothing.
  if ((LOCKED)); then unmount_under "$ROOTFS" || rc=1; fi
  if [ -n "$BUILD_TMP" ]; then  # an unfinished debootstrap: never leave it where the cache goes
    unmount_under "$BUILD_TMP" || true
    rm -rf --one-file-system "$BUILD_TMP"
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
trap 'exit 129' HUP

mkdir -p "$(dirname "$ROOTFS")"
# One run at a time per rootfs: the stale-mount clean-up below would pull mounts from under another run.
exec 9>"$ROOTFS.lock"
if ! flock -n 9; then
  echo "rootfs_test: another run holds $ROOTFS.lock; waiting"
  flock 9
fi
LOCKED=1

# A previous run that was killed hard (SIGKILL, power loss) may have left its mounts: never mount twice.
if [ -n "$(mounts_under "$ROOTFS")" ]; then
  echo "rootfs_test: removing stale mounts from an earlier run"
  unmount_under "$ROOTFS"
fi

t_start=$(date +%s)

# The rootfs: built into a temporary directory and renamed only once debootstrap succeeded, so an
# existing $ROOTFS is always complete.
if [ ! -d "$ROOTFS" ]; then
  if ! command -v debootstrap >/dev/null; then
    echo "rootfs_test: installing debootstrap on the host"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends debootstrap
  fi
  BUILD_TMP=$(mktemp -d "$ROOTFS.tmp.XXXXXX")
  chmod 755 "$BUILD_TMP"
  echo "rootfs_test: debootstrap $SUITE into $BUILD_TMP (a few minutes, once)"
  debootstrap --variant=minbase "$SUITE" "$BUILD_TMP" "$MIRROR" >"$BUILD_TMP.log" 2>&1 || {
    tail -n 30 "$BUILD_TMP.log" >&2
    echo "rootfs_test: debootstrap failed (log: $BUILD_TMP.log)" >&2
    exit 1
  }
  rm -f "$BUILD_TMP.log"
  mv -T "$BUILD_TMP" "$ROOTFS"
  BUILD_TMP=""
  echo "rootfs_test: rootfs built in $(($(date +%s) - t_start)) s: $ROOTFS"
fi
[ -x "$ROOTFS/usr/bin/apt-get" ] || { echo "rootfs_test: $ROOTFS is not a Debian rootfs; delete it" >&2; exit 1; }

# Host files the chroot needs for the network. rm first: a symlink in the rootfs (e.g. resolv.conf
# -> /run/...) would otherwise make cp write to the host's file.
for f in resolv.conf hosts; do
  rm -f "$ROOTFS/etc/$f"
  cp -L "/etc/$f" "$ROOTFS/etc/$f"
done
# HTTPS from the chroot leaves through the host's network, which may need the host's CAs (a
# TLS-inspecting proxy): give pip the host's bundle.
host_ca=""
if [ -s /etc/ssl/certs/ca-certificates.crt ]; then
  mkdir -p "$ROOTFS/etc/brainmech"
  cp -L /etc/ssl/certs/ca-certificates.crt "$ROOTFS/etc/brainmech/host-ca-certificates.crt"
  host_ca=/etc/brainmech/host-ca-certificates.crt
fi
# No service of a package installed in the chroot may start on the host.
printf '#!/bin/sh\nexit 101\n' >"$ROOTFS/usr/sbin/policy-rc.d"
chmod 755 "$ROOTFS/usr/sbin/policy-rc.d"

# Non-recursive binds made private: unmounting them can never propagate back to the host's mounts.
bind() {
  mkdir -p "$2"
  mount --bind "$1" "$2"
  mount --make-private "$2"
}
bind /proc "$ROOTFS/proc"
bind /sys "$ROOTFS/sys"
bind /dev "$ROOTFS/dev"
bind /dev/pts "$ROOTFS/dev/pts"
# A fresh /dev/shm, as Docker gives a container: OpenMPI's shared-memory transport puts its segments there.
mkdir -p "$ROOTFS/dev/shm"
mount -t tmpfs -o mode=1777,nosuid,nodev shm "$ROOTFS/dev/shm"
bind "$REPO" "$ROOTFS/app"

# A clean environment inside: nothing of the host's (venv, PYTHONPATH, pip's local indexes) leaks in.
CHROOT_ENV=(
  HOME=/root
  PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
  LANG=C.UTF-8
  TERM="${TERM:-dumb}"
  VENV=/opt/brainmech/venv
  # /app is the host's work tree: no root-owned bytecode or caches of another Python in it.
  PYTHONDONTWRITEBYTECODE=1
  PYTEST_ADDOPTS="-p no:cacheprovider"
  RUFF_CACHE_DIR=/root/.cache/ruff
  # OpenMPI 5 (trixie) as root, one node. The same values as the Dockerfile's ENV. btl: only
  # shared memory ('vader' is now 'sm'); left to itself the tcp btl loads too and warns "Unable
  # to find reachable pairing between local and remote interfaces". pml ob1: the one that drives
  # the btls; no probing of ucx/cm (psm2, ofi) for hardware that is not there.
  OMPI_ALLOW_RUN_AS_ROOT=1
  OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
  "OMPI_MCA_btl=self,sm"
  OMPI_MCA_pml=ob1
)
if [ -n "$host_ca" ]; then
  CHROOT_ENV+=(PIP_CERT="$host_ca" SSL_CERT_FILE="$host_ca" REQUESTS_CA_BUNDLE="$host_ca")
fi
for v in PYTEST_ARGS CI http_proxy https_proxy no_proxy HTTP_PROXY HTTPS_PROXY NO_PROXY; do
  if [ -n "${!v:-}" ]; then CHROOT_ENV+=("$v=${!v}"); fi
done
in_chroot() { chroot "$ROOTFS" /usr/bin/env -i "${CHROOT_ENV[@]}" "$@"; }

if ! in_chroot bash /app/docker/install.sh; then
  echo "rootfs_test: set-up failed after $(($(date +%s) - t_start)) s" >&2
  exit 1
fi
t_setup=$(date +%s)
echo "rootfs_test: set-up took $((t_setup - t_start)) s"

rc=0
if (($#)); then
  in_chroot "$@" || rc=$?
else
  in_chroot bash /app/scripts/run_tests.sh || rc=$?
fi
t_end=$(date +%s)
echo "rootfs_test: set-up $((t_setup - t_start)) s, tests $((t_end - t_setup)) s, exit code $rc"
exit "$rc"
