#!/usr/bin/env bash
# Check the two README commands on a bare Debian 12: debootstrap a minimal bookworm, clone this
# checkout's committed HEAD into it (the tests' real files come with it, in tests/data) and run
# `bash scripts/run_demo.sh` there, and with --tests also
# `bash scripts/run_tests.sh`. Needs root and the network (Debian mirror, PyPI). Usage:
#   sudo bash scripts/check_fresh_debian.sh [--tests] [ROOT]
# ROOT defaults to /tmp/colmap-citymodel-bookworm; one from an earlier run is reused as it is
# (remove it for a bare start).
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"

tests=0
if [ "${1:-}" = "--tests" ]; then
  tests=1
  shift
fi
root="${1:-/tmp/colmap-citymodel-bookworm}"
if [ "$(id -u)" -ne 0 ]; then
  echo "error: debootstrap and chroot need root" >&2
  exit 1
fi
command -v debootstrap >/dev/null 2>&1 || apt-get install -y --no-install-recommends debootstrap

if [ ! -x "$root/bin/bash" ]; then
  debootstrap --variant=minbase bookworm "$root" http://deb.debian.org/debian
  # Certificates the host adds to Debian's own (a proxy's, for instance) reach the chroot's
  # store when the set-up installs ca-certificates there.
  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    mkdir -p "$root/usr/local/share/ca-certificates"
    cp /usr/local/share/ca-certificates/*.crt "$root/usr/local/share/ca-certificates/"
  fi
fi
cp /etc/resolv.conf "$root/etc/resolv.conf"
rm -rf "$root/work/colmap-citymodel"
mkdir -p "$root/work"
git clone -q "$repo" "$root/work/colmap-citymodel"

mounted=()
cleanup() {
  for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do umount -R "${mounted[i]}" || true; done
}
trap cleanup EXIT
mount -t proc proc "$root/proc"
mounted+=("$root/proc")
for dir in sys dev; do
  mount --rbind "/$dir" "$root/$dir"
  mounted+=("$root/$dir")
done

commands="bash scripts/run_demo.sh"
if [ "$tests" -eq 1 ]; then
  commands="$commands && bash scripts/run_tests.sh -q"
fi
path=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
chroot "$root" /usr/bin/env HOME=/root PATH="$path" \
  /bin/bash -c "cd /work/colmap-citymodel && $commands"
