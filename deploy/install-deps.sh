#!/usr/bin/env bash
# Installs the Debian 12 packages egoslam builds against (OpenCV with its headers, clang for
# the opencv crate's binding generator, protoc for prost) and tests with (systemd-analyze for
# the unit checks). Idempotent: does nothing when all are present. Uses sudo when not root.
set -euo pipefail
packages=(libopencv-dev clang libclang-dev protobuf-compiler pkg-config systemd)
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
echo "installing: ${missing[*]}" >&2
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
