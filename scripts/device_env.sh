# Source ON the GPU machine after .dev/prelude.sh. The project is on PYTHONPATH but not pip-installed, so
# nerfstudio cannot see its entry point (ns-train would exit 2 with "hpgs" unknown); the LPIPS weights come
# from .dev/extra (scripts/device_setup.sh).
export NERFSTUDIO_METHOD_CONFIGS=hpgs=hpgs_ns.method_config:hpgs
export PYTHONPATH=$PYTHONPATH:$PWD/.dev/extra
