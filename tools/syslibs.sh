#!/usr/bin/env bash
# System packages from Debian/Ubuntu, installed when missing (with sudo when not root and sudo
# exists). `demo`: what the demo needs, EGL, through which the simulator renders headless (Mesa's
# software rasteriser when there is no GPU). `test`: also libusb-1.0 (pyrealsense2, the camera
# service's RealSense backend, loads it) and Debian's chromium + chromium-driver, which the
# operator page's tests drive through selenium.
set -euo pipefail
want="${1:-test}"
case "$want" in demo|test) ;; *) echo "usage: $0 demo|test" >&2; exit 2 ;; esac
libs="$( { ldconfig -p 2>/dev/null || /sbin/ldconfig -p; } )"
pkgs=""
grep -q libEGL.so.1 <<<"$libs" || pkgs="$pkgs libegl1 libgl1-mesa-dri libgles2"
if [ "$want" = test ]; then
  grep -q libusb-1.0.so.0 <<<"$libs" || pkgs="$pkgs libusb-1.0-0"
  command -v chromium >/dev/null || pkgs="$pkgs chromium"
  command -v chromedriver >/dev/null || pkgs="$pkgs chromium-driver"
fi
[ -z "$pkgs" ] && exit 0
sudo=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null; then sudo=sudo; fi
echo "missing system packages: installing$pkgs"
$sudo apt-get update
$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $pkgs
