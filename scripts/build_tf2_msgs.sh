#!/usr/bin/env bash
# Build the minimal tf2_msgs (TFMessage only, scripts/tf2_msgs) into a venv of the ROS 2 Jazzy
# PyPI wheels, which have no tf2_msgs. Skipped when tf2_msgs already imports (a ROS install:
# its own tf2_msgs is the one to use, and is never shadowed). Needs cmake, make and a C/C++
# compiler; the build tools come from requirements/tf2_msgs_build.txt.
#
# Usage: scripts/build_tf2_msgs.sh VENV
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$(cd "$1" && pwd)"
python="$venv/bin/python"

if "$python" -c 'import tf2_msgs.msg' 2>/dev/null; then
    echo "build_tf2_msgs: tf2_msgs already importable ($("$python" -c \
        'import tf2_msgs, os; print(os.path.dirname(tf2_msgs.__file__))')): not built" >&2
    exit 0
fi
for tool in cmake make c++; do
    command -v "$tool" >/dev/null || {
        echo "build_tf2_msgs: $tool not found: install cmake, make and g++ (Debian:" \
            "apt install cmake g++ make) to build tf2_msgs" >&2
        exit 1
    }
done

"$python" -m pip --disable-pip-version-check --no-input install \
    -r "$root/requirements/tf2_msgs_build.txt"
build="$(mktemp -d)"
trap 'rm -rf "$build"' EXIT
# The venv prefix is the ROS prefix of the wheels (share/<pkg>/cmake, lib, include).
export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv" PATH="$venv/bin:$PATH"
echo "build_tf2_msgs: building tf2_msgs (TFMessage) into $venv" >&2
cmake -S "$root/scripts/tf2_msgs" -B "$build" -DCMAKE_INSTALL_PREFIX="$venv" \
    -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$python" >"$build/cmake.log" 2>&1 \
    || { cat "$build/cmake.log" >&2; exit 1; }
cmake --build "$build" -j 2 >"$build/build.log" 2>&1 || { tail -50 "$build/build.log" >&2; exit 1; }
cmake --install "$build" >/dev/null
"$python" -c 'from tf2_msgs.msg import TFMessage; TFMessage()'
echo "build_tf2_msgs: done" >&2
