#!/usr/bin/env bash
# Installs the Debian 12 packages egoslam builds against (OpenCV with its headers, clang for
# the opencv crate's binding generator, protoc for prost) and tests with (systemd-analyze for
# the unit checks, openssl for the TLS tests' certificates). Idempotent: does nothing when
# all are present. Uses sudo when not root.
set -euo pipefail
packages=(libopencv-dev clang libclang-dev protobuf-compiler pkg-config systemd openssl)
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
python3 -c "import venv, ensurepip" >/dev/null 2>&1 || missing+=(python3 python3-venv)
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing: ${missing[*]}" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi
# The Python client (clients/python) and its test run in a virtual environment of their
# own (target/python), never in the system's Python; the package is reinstalled each time
# so that the tests use the source as it is.
repo="$(cd "$(dirname "$0")/.." && pwd)"
venv="$repo/target/python"
if ! "$venv/bin/python" -c "import zenoh, google.protobuf" >/dev/null 2>&1; then
  echo "installing: clients/python/requirements.txt into $venv" >&2
  python3 -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    -r "$repo/clients/python/requirements.txt"
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  --force-reinstall "$repo/clients/python"
rm -rf "$repo/clients/python/build" "$repo"/clients/python/src/*.egg-info
