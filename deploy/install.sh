#!/usr/bin/env bash
# Installs egoslam as systemd services on the wearable box (Debian 12), as root:
#   ./deploy/install.sh [path/to/egoslam]      (default: target/release/egoslam, built if absent)
# The services' lean binaries (egoslam-frontend, -solver, -merger) are taken from next to it.
# Creates the system user `egoslam` (groups: video), installs the binaries to
# /usr/local/bin, the units to /etc/systemd/system, and the configuration to /etc/egoslam
# (an existing egoslam.toml is kept). Then: edit /etc/egoslam/egoslam.toml (input.path,
# input.calibration) and `systemctl enable --now egoslam.target`. See docs/deploy.md.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "$(id -u)" -ne 0 ]; then echo "run as root" >&2; exit 1; fi
binary="${1:-target/release/egoslam}"
services=(frontend solver merger)
if [ ! -x "$binary" ]; then
  ./deploy/install-deps.sh
  cargo build --release -p egoslam
fi
# The lean binaries must come from the same build as egoslam (the camera unit runs egoslam
# itself): present, and not older than it by more than a build's linking takes.
for s in "${services[@]}"; do
  lean="$(dirname "$binary")/egoslam-$s"
  if [ ! -x "$lean" ] || [ $(( $(stat -c %Y "$binary") - $(stat -c %Y "$lean") )) -gt 120 ]; then
    echo "$lean missing or older than $binary: build all of egoslam's binaries (cargo build --release -p egoslam)" >&2
    exit 1
  fi
done
if ! id egoslam >/dev/null 2>&1; then
  useradd --system --no-create-home --home-dir /var/lib/egoslam --shell /usr/sbin/nologin egoslam
fi
getent group video >/dev/null && usermod -a -G video egoslam
install -m 0755 "$binary" /usr/local/bin/egoslam
for s in "${services[@]}"; do install -m 0755 "$(dirname "$binary")/egoslam-$s" /usr/local/bin/; done
install -d -m 0755 /etc/egoslam
[ -e /etc/egoslam/egoslam.toml ] || install -m 0644 deploy/egoslam.toml /etc/egoslam/egoslam.toml
# The units' iceoryx2 files live in their runtime directory, not in the shared /tmp.
sed 's|^root-path = .*|root-path = "/run/egoslam/iceoryx2/"|' config/iceoryx2.toml > /etc/egoslam/iceoryx2.toml
chmod 0644 /etc/egoslam/iceoryx2.toml
install -m 0644 deploy/systemd/*.service deploy/systemd/egoslam.target /etc/systemd/system/
install -d -m 0755 /usr/share/doc/egoslam
install -m 0644 docs/deploy.md /usr/share/doc/egoslam/deploy.md
systemd-analyze verify /etc/systemd/system/egoslam-*.service /etc/systemd/system/egoslam.target
systemctl daemon-reload
echo "installed; edit /etc/egoslam/egoslam.toml, then: systemctl enable --now egoslam.target"
