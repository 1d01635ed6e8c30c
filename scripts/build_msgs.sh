#!/usr/bin/env bash
# Build the interface package tetra_gradiometer_msgs/ into a venv's prefix (make setup):
#   scripts/build_msgs.sh VENV BUILD_DIR
# plain cmake with the venv's ros-jazzy-* wheels (docs/ros.md, *Our interfaces*), installed
# where the venv's Python finds it with no variables.
#
# The installed files are cached, as uv caches wheels and mypy its checks, in
# ${XDG_CACHE_HOME:-$HOME/.cache}/tetra_gradiometer/msgs, keyed by everything the build reads:
# the package's files, the venv's installed distributions, its Python, cmake and the compiler.
# A fresh clone on a machine that built the same package copies them (~1 s) instead of
# building (~19 s: cmake's configure ~5 s, then eight typesupport libraries). Two installed
# files name the prefix they were installed under (ament's parent prefix path, the cmake
# export of the Python target's include directories): rewritten to this venv's.
set -euo pipefail
venv=$(cd "$1" && pwd) build=$2
msgs=tetra_gradiometer_msgs
cache=${XDG_CACHE_HOME:-$HOME/.cache}/tetra_gradiometer/msgs
key=$( {
  cat "$msgs"/CMakeLists.txt "$msgs"/package.xml "$msgs"/msg/*.msg "$msgs"/srv/*.srv
  ls "$venv"/lib/python*/site-packages | grep -E '\.dist-info$' | LC_ALL=C sort
  "$venv/bin/python" -VV
  cmake --version | head -n 1
  c++ --version | head -n 1
  cat "$0"
} | sha256sum | cut -c1-24 )
tarball=$cache/$key.tar

# A cached install that cannot be read whole is built again.
if [ -f "$tarball" ] && [ -f "$cache/$key.prefix" ] && tar -tf "$tarball" > /dev/null 2>&1; then
  old=$(cat "$cache/$key.prefix")
  tar -xf "$tarball" -C "$venv"
  tar -tf "$tarball" | (cd "$venv" && xargs grep -lF "$old" 2>/dev/null || true) \
    | (cd "$venv" && xargs -r sed -i "s#$old#$venv#g")
  exit 0
fi

export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv"
cmake -S "$msgs" -B "$build" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
  -DCMAKE_PREFIX_PATH="$venv" -DPython3_EXECUTABLE="$venv/bin/python" > /dev/null
cmake --build "$build" -j "$(nproc)" > "$build/make.log" || { tail -n 30 "$build/make.log"; exit 1; }
cmake --install "$build" --prefix "$venv" > /dev/null

# Into the cache (best effort: a cache that cannot be written costs the next clone a build):
# the installed files relative to the prefix, written whole, then renamed.
sed "s#^$venv/##" "$build/install_manifest.txt" > "$build/installed.txt"
{ mkdir -p "$cache" && tar -cf "$tarball.$$" -C "$venv" -T "$build/installed.txt" \
    && echo "$venv" > "$cache/$key.prefix" && mv "$tarball.$$" "$tarball"; } 2> /dev/null \
  || { rm -f "$tarball.$$"; echo "warning: the interface package was not cached in $cache"; }
