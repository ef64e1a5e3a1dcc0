#!/usr/bin/env bash
# Install what the tests need on a fresh machine, then lint, type-check (mypy, configured in pyproject.toml),
# build the documentation site (warnings are errors) and run the whole suite.
# Debian packages (user-mode Linux for the vcan tests; systemd and dbus for the unit checks
# and the systemd guest tier; python3-venv for its install test; libsodium for the firmware's
# signature check) are installed with apt-get when running as root and missing.
set -euo pipefail
cd "$(dirname "$0")/.."

need=()
command -v linux.uml >/dev/null 2>&1 || need+=(user-mode-linux)
command -v insmod >/dev/null 2>&1 || need+=(kmod)
command -v ip >/dev/null 2>&1 || need+=(iproute2)
command -v systemd-analyze >/dev/null 2>&1 && [ -x /lib/systemd/systemd ] || need+=(systemd)
command -v dbus-daemon >/dev/null 2>&1 || need+=(dbus)
/usr/bin/python3 -c 'import ensurepip, venv' >/dev/null 2>&1 || need+=(python3-venv)
command -v cc >/dev/null 2>&1 || need+=(gcc libc6-dev)
# the firmware's signature check is built against the distribution's libsodium in the tests
[ -e /usr/lib/x86_64-linux-gnu/libsodium.so.23 ] || need+=(libsodium23)  # the path the test links
if [ "${#need[@]}" -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    echo "installing Debian packages: ${need[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "warning: not root, cannot apt-get install ${need[*]}" >&2
  fi
fi

# --upgrade-strategy eager: the newest versions pyproject.toml allows, as a fresh machine gets them, not
# whatever an older run left installed (a machine that kept an old pytest passed where a new one failed)
python3 -m pip install -q --disable-pip-version-check --upgrade --upgrade-strategy eager -e '.[test,docs]'
ruff check canical tests docs
python3 -m mypy
python3 -m vulture  # dead code ([tool.vulture] in pyproject.toml)
python3 -m mkdocs build --strict --quiet
python3 -m pytest -q -p no:cacheprovider --durations=15 "$@"
