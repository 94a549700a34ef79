#!/usr/bin/env bash
# Wheels for the lent GPU machine (device tool; its image has Python 3.12, torch, numpy, pandas, matplotlib,
# tensorboard, pytest and pytest-xdist, and nothing can be fetched there): the packages this project needs beyond
# them, downloaded here into .whl/ (git-ignored through .git/info/exclude), to be named in the run's `carry`.
#
#   bash scripts/gpu_wheels.sh          # then see scripts/gpu_session.sh
set -euo pipefail
cd "$(dirname "$0")/.."
exclude=$(git rev-parse --git-path info/exclude)
mkdir -p "$(dirname "$exclude")"
grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"
mkdir -p .whl
py=${PYTHON:-python3}
platforms=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
           --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any)
# No dependencies followed: the lists are the closure of what the image lacks (wandb left out: the GPU checks run
# with logger=tensorboard or none). Binary wheels for the machine's Python 3.12 on x86-64 Linux:
pin() {  # NAME==VERSION as installed in this venv (the versions CI tests), NAME alone if it is not installed here
  local name version
  for name in "$@"; do
    version=$("$py" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$name" 2>/dev/null) || version=""
    echo "$name${version:+==$version}"
  done
}
binary=($(pin mujoco-core mujoco-studio glfw greenlet sqlalchemy websockets))  # websockets: mujoco-studio's
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
  -d .whl "${binary[@]}"
# Pure Python, built here when only a source archive exists (antlr4-python3-runtime 4.9.3, which omegaconf pins):
pure=($(pin mujoco stable-baselines3 gymnasium farama-notifications pyopengl absl-py etils hydra-core omegaconf \
      antlr4-python3-runtime hydra-joblib-launcher optuna alembic colorlog mako pytest-timeout))
"$py" -m pip wheel -q --no-deps -w .whl "${pure[@]}"
# SBX's TD3 (the peer of the GPU tables) on the image's JAX: sbx-rl, flax, optax, tfp-nightly and what they import.
# flax's checkpointing (orbax-checkpoint, tensorstore: 23 MB) is left out: SBX trains without it (checked here with
# those modules blocked), and the carry holds 64 MiB in all.
sbx_binary=($(pin msgpack dm-tree pyyaml))
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
  -d .whl "${sbx_binary[@]}"
sbx_pure=($(pin sbx-rl flax optax tfp-nightly treescope rich markdown-it-py mdurl pygments gast cloudpickle decorator six))
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
  -d .whl "${sbx_pure[@]}"
du -sh .whl
# libEGL and friends for MuJoCo's EGL rendering (device README: the image has the NVIDIA driver's EGL, not the loader)
grep -qx '/.gl/' "$exclude" || echo '/.gl/' >> "$exclude"
mkdir -p .gl /tmp/amd64/partial
apt_options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
apt-get "${apt_options[@]}" update > /dev/null
(cd .gl && apt-get "${apt_options[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 > /dev/null)
du -sh .gl
