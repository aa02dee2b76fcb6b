#!/usr/bin/env bash
# Create or refresh .venv at the repository root: the ROS 2 Jazzy Python stack from PyPI wheels,
# the development tools, and quatcal_ros itself in editable mode (so `.venv/bin/python -m
# quatcal_ros` runs the working tree). Idempotent: does nothing while .venv/.bootstrap-stamp is
# newer than the requirement files, setup.py, setup.cfg and package.xml.
#
# Environment: PYTHON=/path/to/python3.11 to choose the interpreter; QUATCAL_FORCE_BOOTSTRAP=1
# to reinstall anyway.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
stamp="$venv/.bootstrap-stamp"
inputs=("$root/requirements/runtime.txt" "$root/requirements/dev.txt"
        "$root/requirements/tf2_msgs_build.txt" "$root/scripts/build_tf2_msgs.sh"
        "$root/scripts/tf2_msgs/CMakeLists.txt" "$root/scripts/tf2_msgs/msg/TFMessage.msg"
        "$root/setup.py" "$root/setup.cfg" "$root/package.xml")

up_to_date() {
    [[ -f "$stamp" && -x "$venv/bin/python" ]] || return 1
    local f
    for f in "${inputs[@]}"; do
        [[ "$stamp" -nt "$f" ]] || return 1
    done
}

if [[ "${QUATCAL_FORCE_BOOTSTRAP:-0}" != 1 ]] && up_to_date; then
    exit 0
fi

# The ROS wheels are built for CPython 3.11 (cp311) only.
python="${PYTHON:-}"
if [[ -z "$python" ]]; then
    python="$(command -v python3.11 || command -v python3 || true)"
fi
if [[ -z "$python" ]] || ! "$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'
then
    echo "bootstrap: need Python 3.11 (the ROS 2 Jazzy wheels are cp311); found:" \
        "${python:-none} $("${python:-false}" --version 2>&1 || true)." \
        "Set PYTHON=/path/to/python3.11." >&2
    exit 1
fi

echo "bootstrap: setting up $venv with $python ($("$python" --version 2>&1))" >&2
if [[ ! -x "$venv/bin/python" ]]; then
    "$python" -m venv "$venv"
fi
rm -f "$stamp"
# Keep colcon (`--base-paths <repo>`) and ament linters out of the venv: its site-packages hold
# many share/<pkg>/package.xml files of the ROS wheels.
touch "$venv/COLCON_IGNORE" "$venv/AMENT_IGNORE"

pip=("$venv/bin/python" -m pip --disable-pip-version-check --no-input)
"${pip[@]}" install -r "$root/requirements/runtime.txt" -r "$root/requirements/dev.txt"
# Editable install of the working tree (PEP 660; --use-pep517, or pip 23 falls back to the
# legacy `setup.py develop`, which obeys setup.cfg and hides the scripts in .venv/lib/quatcal_ros).
# editable_mode=compat puts the repo root on sys.path with a .pth file, so modules added to
# quatcal_ros/ later are found without reinstalling (the default mode maps only the packages that
# exist at install time). The console scripts land in .venv/bin. The build uses the venv's own
# setuptools, which needs `wheel` beside it.
"${pip[@]}" install 'wheel>=0.40'
"${pip[@]}" install --no-build-isolation --no-deps --use-pep517 \
    --config-settings editable_mode=compat -e "$root"

# No wheel of tf2_msgs exists: build TFMessage locally (skipped where tf2_msgs imports).
"$root/scripts/build_tf2_msgs.sh" "$venv"

# Fail now, not in the first test, when the stack does not import.
"$venv/bin/python" -c 'import rclpy, geometry_msgs.msg, std_srvs.srv, diagnostic_msgs.msg, tf2_msgs.msg, numpy, yaml, rosbags'

touch "$stamp"
echo "bootstrap: done" >&2
