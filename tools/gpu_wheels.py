"""Fetch the wheels a GPU machine without network needs for tools/gpu_run.sh, into .whl/.

    python tools/gpu_wheels.py [--python-version 3.12] [--dest .whl]

Downloads mitsuba 3.9.1, drjit 1.5.0, OpenEXR and flip-evaluator for that Python on
manylinux x86-64 (pip download, no dependencies: numpy, matplotlib and tqdm are assumed there),
then repacks the mitsuba wheel without what a ``cuda_ad_rgb`` run does not load, since a device
call carries at most 64 MiB together with the working tree: the spectral, mono and polarized
variant modules, ``llvm_ad_rgb`` (the GPU run uses ``cuda_ad_rgb``), the C++ headers, CMake files
and docs, the spectral upsampling table ``data/srgb.coeff`` (read by spectral variants only)
and plugins no scene here uses (:data:`UNUSED_PLUGINS`): mitsuba's wheel for Python 3.12 went
62.6 → 31.5 MB in session 13, 38.6 MB of wheels in all. The wheel's RECORD loses the dropped
files' lines, so pip installs it as usual.
"""
import argparse
import glob
import os
import re
import subprocess
import sys
import zipfile

PACKAGES = ("mitsuba==3.9.1", "drjit==1.5.0", "OpenEXR", "flip-evaluator==1.7")
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64")
#: variant modules, headers and build files a cuda_ad_rgb run never loads
DROP = re.compile(r"^mitsuba/(\w+_(mono|spectral)\w*\.cpython[^/]*|llvm_ad_rgb\.cpython[^/]*"
                  r"|include/.*|cmake/.*|doc/.*|data/srgb\.coeff)$")
#: plugins no scene of scenes_xml/ or ../shared/scenes/ and no integrator of the suite uses
UNUSED_PLUGINS = ("ellipsoids", "ellipsoidsmesh", "volpathmis", "bsplinecurve", "linearcurve",
                  "sdfgrid", "sunsky", "timed_sunsky", "prbvolpath", "aov", "stokes",
                  "polarizer", "retarder", "measured", "measured_polarized", "pplastic",
                  "blendbsdf", "hair", "principledthindielectric", "spiral", "gridvolume")


def dropped(name: str) -> bool:
    """Whether the repacked mitsuba wheel leaves ``name`` out."""
    if DROP.match(name):
        return True
    m = re.match(r"^mitsuba/plugins/(\w+)\.so$", name)
    return bool(m) and m.group(1) in UNUSED_PLUGINS


def repack(wheel: str) -> tuple:
    """Rewrite ``wheel`` in place without the :func:`dropped` files; returns (files dropped,
    bytes before, bytes after)."""
    before = os.path.getsize(wheel)
    tmp = wheel + ".tmp"
    with zipfile.ZipFile(wheel) as zi, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED,
                                                       compresslevel=9) as zo:
        gone = {n for n in zi.namelist() if dropped(n)}
        for info in zi.infolist():
            if info.filename in gone:
                continue
            data = zi.read(info)
            if info.filename.endswith(".dist-info/RECORD"):
                lines = [ln for ln in data.decode().splitlines() if ln.split(",")[0] not in gone]
                data = ("\n".join(lines) + "\n").encode()
            zo.writestr(info, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
    os.replace(tmp, wheel)
    return len(gone), before, os.path.getsize(wheel)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--python-version", default="3.12")
    ap.add_argument("--dest", default=".whl")
    args = ap.parse_args(argv)
    os.makedirs(args.dest, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
           "--python-version", args.python_version, "--implementation", "cp", "-d", args.dest]
    for platform in PLATFORMS:
        cmd += ["--platform", platform]
    subprocess.run(cmd + list(PACKAGES), check=True)
    tag = "cp" + args.python_version.replace(".", "")
    for wheel in glob.glob(os.path.join(args.dest, f"mitsuba-*-{tag}-*.whl")):
        n, before, after = repack(wheel)
        print(f"{os.path.basename(wheel)}: {n} files dropped, {before / 1e6:.1f} -> "
              f"{after / 1e6:.1f} MB")
    total = sum(os.path.getsize(w) for w in glob.glob(os.path.join(args.dest, "*.whl")))
    print(f"{args.dest}: {total / 1e6:.1f} MB of wheels (a device call carries at most 64 MiB "
          f"with the working tree)")


if __name__ == "__main__":
    main()
