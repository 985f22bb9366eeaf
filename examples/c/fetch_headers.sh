#!/usr/bin/env bash
# Put onnxruntime's C headers into $1 (default: build/onnxruntime): they ship in no PyPI package,
# so this downloads Debian's libonnxruntime-dev (trixie) with apt through a private sources list
# and unpacks only its headers. Nothing is installed on the system and nothing third-party is
# committed. Any header version at or below the library's API version works (the wheel's
# libonnxruntime accepts every older C API version); trixie's 1.21 headers need onnxruntime >= 1.21.
set -euo pipefail
dest=${1:-build/onnxruntime}
if [ -f "$dest/include/onnxruntime_c_api.h" ]; then exit 0; fi
if ! command -v apt-get >/dev/null || ! command -v dpkg-deb >/dev/null; then
    echo "error: fetching onnxruntime's C headers needs apt-get and dpkg-deb (Debian/Ubuntu); put onnxruntime_c_api.h" \
         "of onnxruntime <= the wheel's version into $dest/include yourself" >&2
    exit 2
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/lists/partial" "$work/archives/partial"
echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] http://deb.debian.org/debian trixie main" \
    > "$work/sources.list"
apt_opts=(-q -o "Dir::Etc::SourceList=$work/sources.list" -o Dir::Etc::SourceParts=/dev/null
          -o "Dir::State::Lists=$work/lists" -o "Dir::Cache::Archives=$work/archives" -o Debug::NoLocking=1
          -o APT::Sandbox::User=root)
if ! apt-get "${apt_opts[@]}" update >"$work/log" 2>&1 \
        || ! (cd "$work" && apt-get "${apt_opts[@]}" download libonnxruntime-dev >>"$work/log" 2>&1); then
    echo "error: could not download Debian's libonnxruntime-dev (onnxruntime's C headers) from deb.debian.org:" \
         "$(tail -n 1 "$work/log")" >&2
    exit 2
fi
dpkg-deb -x "$work"/libonnxruntime-dev_*.deb "$work/root"
mkdir -p "$dest/include"
cp "$work"/root/usr/include/onnxruntime/*.h "$dest/include/"
echo "onnxruntime C headers $(basename "$work"/libonnxruntime-dev_*.deb .deb | cut -d_ -f2) in $dest/include"
