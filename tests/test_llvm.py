"""The libLLVM search (mi_twopass/_llvm.py), on fake directory trees."""
import os

import pytest

from mi_twopass import _llvm


def touch(d, name):
    os.makedirs(d, exist_ok=True)
    open(os.path.join(d, name), "w").close()


@pytest.mark.parametrize("name,major", [
    ("libLLVM-19.so", 19), ("libLLVM.so.19.1", 19), ("libLLVM-14.0.6.so.1", 14),
    ("libLLVM-15.so.1", 15), ("libLLVMSupport.a", None), ("libc.so.6", None),
])
def test_llvm_major_from_name(name, major):
    assert _llvm.llvm_major(name) == major


def test_picks_newest_usable(tmp_path):
    d = str(tmp_path / "lib")
    for n in ("libLLVM-14.so", "libLLVM-15.so.1", "libLLVM.so.19.1", "libLLVM-17.so"):
        touch(d, n)
    best, found = _llvm.find_libllvm((d,))
    assert best == os.path.join(d, "libLLVM.so.19.1")
    assert len(found) == 4


def test_glob_dirs(tmp_path):
    touch(str(tmp_path / "llvm-18" / "lib"), "libLLVM-18.so")
    touch(str(tmp_path / "llvm-15" / "lib"), "libLLVM-15.so")
    best, _ = _llvm.find_libllvm((str(tmp_path / "llvm-*" / "lib"),))
    assert best.endswith("llvm-18/lib/libLLVM-18.so")


def test_only_llvm15_fails_with_fix(tmp_path):
    d = str(tmp_path)
    touch(d, "libLLVM-15.so.1")
    env = {}
    with pytest.raises(_llvm.LLVMNotFoundError) as e:
        _llvm.configure(env, (d,), platform="linux")
    msg = str(e.value)
    assert "apt-get install -y libllvm19" in msg and "DRJIT_LIBLLVM_PATH" in msg
    assert "libLLVM-15.so.1" in msg  # says what it found
    assert "DRJIT_LIBLLVM_PATH" not in env


def test_configure_sets_env(tmp_path):
    touch(str(tmp_path), "libLLVM-19.so")
    env = {}
    path = _llvm.configure(env, (str(tmp_path),), platform="linux")
    assert env["DRJIT_LIBLLVM_PATH"] == path == str(tmp_path / "libLLVM-19.so")


def test_user_setting_wins(tmp_path):
    env = {"DRJIT_LIBLLVM_PATH": "/opt/my/libLLVM.so"}
    assert _llvm.configure(env, (str(tmp_path),), platform="linux") == "/opt/my/libLLVM.so"
    assert env["DRJIT_LIBLLVM_PATH"] == "/opt/my/libLLVM.so"


def test_non_linux_left_alone(tmp_path):
    env = {}
    assert _llvm.configure(env, (str(tmp_path),), platform="darwin") is None
    assert env == {}


def test_import_configured_a_working_llvm():
    """In this process `import mi_twopass` ran before drjit started, and kernels run."""
    import drjit as dr
    import mitsuba as mi

    assert os.environ.get("DRJIT_LIBLLVM_PATH")
    x = dr.minimum(mi.Float([1.0, 5.0]), mi.Float([3.0, 2.0]))  # fminimum crashed LLVM 15
    assert list(x) == [1.0, 2.0]
