"""fppsim.dataio.readers.load_psp_mat / fppsim.dataio.writers.save_psp_mat: the PSin / PCos / fringe-order .mat layout shares one code path with fppsim.phase.psp."""

import numpy as np
import pytest
import scipy.io

from fppsim.phase import psp
from _helpers import synthesize_stack
from fppsim.errors import PSPMatError
from fppsim.dataio.readers import load_psp_mat
from fppsim.dataio.writers import save_psp_mat

TWO_PI = 2 * np.pi


@pytest.fixture
def simulated():
    """Phase-shifted stacks of a ramp over the projector at (1, 8, 80) periods, 8-bit-like values."""
    W = 912
    u = np.linspace(3, W - 4, 40 * 50).reshape(40, 50)
    wrapped = {}
    for f in (1, 8, 80):
        stack = synthesize_stack(TWO_PI * f * u / W, 110.0, 70.0, n_steps=4)
        wrapped[f] = stack
    un = psp.unwrap_temporal({f: psp.wrapped_phase(s).phase for f, s in wrapped.items()})
    psin, pcos = psp.phase_sums(wrapped[80])
    return dict(stack=wrapped[80], psin=psin, pcos=pcos, un=un, truth=TWO_PI * 80 * u / W)


def test_round_trip_same_phase_as_psp(tmp_path, simulated):
    path = tmp_path / "scan.mat"
    save_psp_mat(path, simulated["psin"], simulated["pcos"], simulated["un"].order, n_steps=4, periods=80)
    data = load_psp_mat(path)
    assert data.keys == {"sin": "PSin", "cos": "PCos", "order": "Order"}
    assert data.meta == {"n_steps": 4, "periods": 80.0}
    np.testing.assert_array_equal(data.psin, simulated["psin"])
    np.testing.assert_array_equal(data.order, simulated["un"].order)
    assert data.order.dtype == np.int64 and data.phase.dtype == np.float64
    np.testing.assert_array_equal(data.wrapped, psp.wrapped_phase(simulated["stack"]).phase)
    np.testing.assert_allclose(data.phase, simulated["un"].phase, atol=1e-9)
    np.testing.assert_allclose(data.phase, simulated["truth"], atol=1e-9)
    np.testing.assert_allclose(data.modulation, 70.0, atol=1e-9)
    assert data.valid.all() and data.path == str(path)
    assert not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize("keys", [("psin", "pcos", "k"), ("numerator", "denominator", "fringe_order"),
                                  ("PS", "PC", "K"), ("PSIN", "PCOS", "ORDER"), ("Psin", "Pcos", "FringeOrder")])
def test_key_spellings(tmp_path, simulated, keys):
    path = tmp_path / "k.mat"
    save_psp_mat(path, simulated["psin"], simulated["pcos"], simulated["un"].order, keys=keys)
    data = load_psp_mat(path)
    assert tuple(data.keys.values()) == keys
    np.testing.assert_allclose(data.phase, simulated["un"].phase, atol=1e-9)
    assert data.modulation is None


def test_explicit_keys_matlab_layout_and_sign_option(tmp_path, simulated):
    # a file as MATLAB would write it: doubles, orders stored as double, extra variables
    path = tmp_path / "lab.mat"
    scipy.io.savemat(path, {"a": -simulated["psin"], "b": simulated["pcos"],
                            "c": simulated["un"].order.astype(float), "note": "lab scan", "img": np.zeros((2, 2))})
    with pytest.raises(PSPMatError, match=r"lab\.mat: no sin variable .*variables: a, b, c, note, img"):
        load_psp_mat(path)
    data = load_psp_mat(path, sin_key="a", cos_key="b", order_key="c", negate_sin=True)
    np.testing.assert_allclose(data.phase, simulated["un"].phase, atol=1e-9)
    assert data.meta == {"note": "lab scan"}
    with pytest.raises(PSPMatError, match="no variable 'zz' for order"):
        load_psp_mat(path, sin_key="a", cos_key="b", order_key="zz")


def test_nan_pixels_are_invalid(tmp_path, simulated):
    psin, order = simulated["psin"].copy(), simulated["un"].order.astype(float)
    psin[0, 0] = np.nan
    order[1, 1] = np.nan
    path = tmp_path / "nan.mat"
    scipy.io.savemat(path, {"PSin": psin, "PCos": simulated["pcos"], "Order": order})
    data = load_psp_mat(path)
    assert not data.valid[0, 0] and not data.valid[1, 1] and data.valid.sum() == data.valid.size - 2
    assert np.isnan(data.phase[0, 0]) and np.isnan(data.phase[1, 1]) and data.order[1, 1] == 0


def test_errors(tmp_path, simulated):
    s, c, k = simulated["psin"], simulated["pcos"], simulated["un"].order
    p = tmp_path / "bad.mat"
    scipy.io.savemat(p, {"PSin": s, "PCos": c[:, :10], "Order": k})
    with pytest.raises(PSPMatError, match=r"bad\.mat: shapes differ: PSin \(40, 50\), PCos \(40, 10\)"):
        load_psp_mat(p)
    scipy.io.savemat(p, {"PSin": s, "PCos": c, "Order": k + 0.25})
    with pytest.raises(PSPMatError, match="not integer at 2000 pixels"):
        load_psp_mat(p)
    scipy.io.savemat(p, {"PSin": s, "PCos": c})
    with pytest.raises(PSPMatError, match=r"bad\.mat: no order variable .*variables: PSin, PCos"):
        load_psp_mat(p)
    scipy.io.savemat(p, {"PSin": s, "PCos": c, "Order": "abc"})
    with pytest.raises(PSPMatError, match="not a real numeric array"):
        load_psp_mat(p)
    with pytest.raises(PSPMatError, match="no such file"):
        load_psp_mat(tmp_path / "missing.mat")
    txt = tmp_path / "notmat.mat"
    txt.write_bytes(b"hello world, not a mat file" * 10)
    with pytest.raises(PSPMatError, match="notmat.mat"):
        load_psp_mat(txt)
    with pytest.raises(PSPMatError, match="shapes differ"):
        save_psp_mat(p, s, c, k[:3])
    with pytest.raises(PSPMatError, match="finite integers"):
        save_psp_mat(p, s, c, k + 0.5)


def test_v73_hdf5_file(tmp_path):
    # a MATLAB v7.3 header: 116 bytes of text, 8 bytes subsystem offset, version 0x0200, endian 'IM'
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    p = tmp_path / "v73.mat"
    p.write_bytes(head.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM" + b"\x00" * 512)
    try:
        import h5py  # noqa: F401
    except ImportError:
        with pytest.raises(PSPMatError, match="v7.3 .*install h5py"):
            load_psp_mat(p)
    else:
        with pytest.raises(Exception):
            load_psp_mat(p)  # not a real HDF5 body
