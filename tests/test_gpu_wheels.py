"""tools/gpu_wheels.py: the mitsuba wheel repacked for a cuda_ad_rgb run keeps what that run
loads and a RECORD that lists only what is left."""
import importlib.util
import os
import zipfile

_PATH = os.path.join(os.path.dirname(__file__), "..", "tools", "gpu_wheels.py")
_spec = importlib.util.spec_from_file_location("gpu_wheels", _PATH)
gpu_wheels = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gpu_wheels)

KEPT = ["mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so",
        "mitsuba/scalar_rgb.cpython-312-x86_64-linux-gnu.so",
        "mitsuba/mitsuba_ext.cpython-312-x86_64-linux-gnu.so", "mitsuba/libmitsuba.so",
        "mitsuba/plugins/path.so", "mitsuba/plugins/diffuse.so", "mitsuba/plugins/bitmap.so",
        "mitsuba/python/util.py", "mitsuba/__init__.py"]
DROPPED = ["mitsuba/cuda_ad_spectral.cpython-312-x86_64-linux-gnu.so",
           "mitsuba/llvm_ad_mono_polarized.cpython-312-x86_64-linux-gnu.so",
           "mitsuba/scalar_spectral.cpython-312-x86_64-linux-gnu.so",
           "mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so", "mitsuba/include/mitsuba.h",
           "mitsuba/data/srgb.coeff", "mitsuba/plugins/sunsky.so"]


def test_dropped_keeps_what_a_cuda_rgb_run_loads():
    assert not any(gpu_wheels.dropped(n) for n in KEPT)
    assert all(gpu_wheels.dropped(n) for n in DROPPED)


def test_repack_leaves_the_kept_files_and_their_record(tmp_path):
    wheel = tmp_path / "mitsuba-3.9.1-cp312-cp312-manylinux_2_28_x86_64.whl"
    record = "mitsuba-3.9.1.dist-info/RECORD"
    with zipfile.ZipFile(wheel, "w") as z:
        for n in KEPT + DROPPED:
            z.writestr(n, b"x" * 100)
        z.writestr(record, "\n".join(f"{n},sha256=0,100" for n in KEPT + DROPPED) + "\n")
    n, before, after = gpu_wheels.repack(str(wheel))
    assert n == len(DROPPED) and after < before
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        listed = {ln.split(",")[0] for ln in z.read(record).decode().splitlines() if ln}
    assert names == set(KEPT) | {record}
    assert listed == set(KEPT)
