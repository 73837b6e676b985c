"""Tests of twoscale.merl: bins ↔ angles, directions, read/write round trip, bad files."""

import time

import jax
import numpy as np
import pytest

from twoscale import geometry as g
from twoscale import merl

INDEX = np.meshgrid(
    np.arange(merl.N_THETA_H), np.arange(merl.N_THETA_D), np.arange(merl.N_PHI_D), indexing="ij"
)


def test_constants():
    assert merl.SHAPE == (90, 90, 180)
    assert merl.FILE_BYTES == 34_992_012 == 12 + 3 * 90 * 90 * 180 * 8
    np.testing.assert_array_equal(merl.SCALE, [1.0 / 1500, 1.15 / 1500, 1.66 / 1500])


def test_reference_file_size(shared_data):
    tsv = shared_data / "merl_reference" / "merl100_lfs_sha256.tsv"
    if not tsv.is_file():
        pytest.skip(f"{tsv} not found")
    lines = tsv.read_text().splitlines()
    assert lines[0].split("\t") == ["material", "sha256", "size_bytes"]
    sizes = {int(line.split("\t")[2]) for line in lines[1:] if line.strip()}
    assert sizes == {merl.FILE_BYTES}
    assert len(lines) - 1 == 100


@pytest.mark.parametrize("convention", merl.CONVENTIONS)
def test_every_bin_round_trips(convention):
    angles = merl.bin_to_angles(*INDEX, convention=convention)
    back = merl.angles_to_bin(*angles)
    for a, b in zip(back, INDEX, strict=True):
        np.testing.assert_array_equal(a, b)
    if convention == "centre":
        # φ_d of the reciprocal pair (φ_d − π, as atan2 returns it) folds back into the same bin.
        # (Not for lower edges: φ_d = 0 becomes −π, which folds to 0 only up to rounding.)
        back = merl.angles_to_bin(angles[0], angles[1], angles[2] - np.pi)
        np.testing.assert_array_equal(back[2], INDEX[2])


def test_bin_angles_values_and_clamping():
    th, td, pd = merl.bin_to_angles(
        np.array([0, 1, 89]), np.array([0, 45, 89]), np.array([0, 90, 179])
    )
    np.testing.assert_allclose(th, np.array([0, 1, 89**2]) / 8100 * np.pi / 2, rtol=1e-15)
    np.testing.assert_allclose(td, np.deg2rad([0, 45, 89]), rtol=1e-15)
    np.testing.assert_allclose(pd, np.deg2rad([0, 90, 179]), rtol=1e-15)
    th, td, pd = merl.bin_to_angles(0, 0, 0, convention="centre")
    np.testing.assert_allclose(
        (th, td, pd), ((0.5 / 90) ** 2 * np.pi / 2, np.pi / 360, np.pi / 360)
    )
    # Out of range angles clamp; negative φ_d folds by +π; φ_d = π clamps to the last bin.
    i = merl.angles_to_bin([-0.1, np.pi / 2, 3.0], [-0.1, np.pi / 2, 3.0], [-np.pi / 2, np.pi, 4.0])
    np.testing.assert_array_equal(i[0], [0, 89, 89])
    np.testing.assert_array_equal(i[1], [0, 89, 89])
    np.testing.assert_array_equal(i[2], [90, 179, 179])
    with pytest.raises(ValueError, match="convention"):
        merl.bin_to_angles(0, 0, 0, convention="center")
    with pytest.raises(ValueError, match="out of range"):
        merl.bin_to_angles(90, 0, 0)
    with pytest.raises(ValueError, match="integer"):
        merl.bin_to_angles(0.5, 0, 0)
    with pytest.raises(ValueError, match="non-finite"):
        merl.angles_to_bin(np.nan, 0.0, 0.0)


@pytest.mark.parametrize("convention", merl.CONVENTIONS)
def test_directions_reproduce_angles(convention):
    data = merl.from_function(lambda wi, wo: np.ones(wi.shape), convention)
    wi, wo = data.directions(convention)
    th, td, pd = data.angles(convention)
    assert wi.shape == wo.shape == (*merl.SHAPE, 3) and wi.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-15)
    # cos θ_i, cos θ_o of docs/model.md §7.3.
    a, b = np.cos(th) * np.cos(td), np.sin(th) * np.sin(td) * np.cos(pd)
    np.testing.assert_allclose(wi[..., 2], a - b, atol=1e-15)
    np.testing.assert_allclose(wo[..., 2], a + b, atol=1e-15)
    # Same directions as the JAX implementation, and back to the angles.
    gi, go = jax.jit(g.dirs_from_half_diff)(th, td, pd)  # jit: one fused pass
    np.testing.assert_allclose(gi, wi, atol=1e-15)
    np.testing.assert_allclose(go, wo, atol=1e-15)
    th2, td2, pd2 = (np.asarray(x) for x in jax.jit(g.half_diff_from_dirs)(wi, wo))
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-12)
    defined = td > 0  # φ_d is undefined at θ_d = 0 (the lower edge of the first θ_d bin)
    np.testing.assert_allclose(pd2[defined], pd[defined], atol=1e-11)
    if convention == "centre":  # bin centres are far from the edges: the whole chain is exact
        for a, b in zip(merl.angles_to_bin(th2, td2, pd2), INDEX, strict=True):
            np.testing.assert_array_equal(a, b)


def test_valid_geometric():
    for convention, frac in (("lower", 0.7623), ("centre", 0.7519)):
        v = merl.valid_geometric(convention)
        assert v.shape == merl.SHAPE and v.dtype == bool
        assert abs(v.mean() - frac) < 1e-4
        wi, wo = merl.MerlData(np.zeros((*merl.SHAPE, 3)), v).directions(convention)
        np.testing.assert_array_equal(v, (wi[..., 2] > 0) & (wo[..., 2] > 0))
    with pytest.raises(ValueError, match="convention"):
        merl.valid_geometric("middle")


def random_raw(rng, invalid=0.242):
    """Raw file body (3, 90, 90, 180): positive values over decades, −1 in invalid cells."""
    raw = np.exp(rng.uniform(-12.0, 8.0, (3, *merl.SHAPE)))
    bad = rng.random(merl.SHAPE) < invalid
    raw[:, bad] = -1.0
    return raw, ~bad


def write_raw(path, raw, header=merl.SHAPE, extra=b""):
    path.write_bytes(np.asarray(header, "<i4").tobytes() + np.asarray(raw, "<f8").tobytes() + extra)
    return path


@pytest.fixture(scope="module")
def raw_file(tmp_path_factory):
    rng = np.random.default_rng(11)
    raw, valid = random_raw(rng)
    path = write_raw(tmp_path_factory.mktemp("merl") / "synthetic-blue.binary", raw)
    return path, raw, valid


def test_read_full_size_file(raw_file):
    path, raw, valid = raw_file
    assert path.stat().st_size == merl.FILE_BYTES
    merl.read(path)  # warm the page cache
    t0 = time.perf_counter()
    data = merl.read(path)
    dt = time.perf_counter() - t0
    print(f"\nmerl.read of a {merl.FILE_BYTES}-byte file: {dt * 1e3:.1f} ms")
    assert dt < 5.0
    assert data.name == "synthetic-blue" and data.path == path
    assert data.values.shape == (*merl.SHAPE, 3) and data.values.dtype == np.float64
    assert data.values.flags.c_contiguous and not data.values.flags.writeable
    np.testing.assert_array_equal(data.valid, valid)
    assert data.valid_fraction == valid.mean()
    expected = np.moveaxis(raw, 0, -1) * merl.SCALE
    np.testing.assert_array_equal(data.values[valid], expected[valid])
    assert np.all(data.values[~valid] == 0.0)
    assert "synthetic-blue" in repr(data)


def test_partially_negative_cell_is_invalid(tmp_path):
    raw = np.ones((3, *merl.SHAPE))
    raw[1, 3, 4, 5] = -1.0  # only G negative
    data = merl.read(write_raw(tmp_path / "x.binary", raw))
    assert not data.valid[3, 4, 5] and data.valid.sum() == merl.N_CELLS - 1
    np.testing.assert_array_equal(data.values[3, 4, 5], 0.0)


def test_write_read_round_trip(raw_file, tmp_path):
    path, raw, valid = raw_file
    data = merl.read(path)
    # Data read from a file survives write → read bit for bit (values and mask).
    out = merl.write(tmp_path / "copy.binary", data)
    assert out.stat().st_size == merl.FILE_BYTES
    back = merl.read(out)
    np.testing.assert_array_equal(back.valid, data.valid)
    np.testing.assert_array_equal(back.values, data.values)
    # The raw body is reproduced within 1 ulp (bit for bit in most cells: x → x·s is not injective,
    # so exact raw identity cannot hold everywhere); invalid cells are −1 in all channels.
    raw2 = np.fromfile(out, "<f8", offset=12).reshape(raw.shape)
    np.testing.assert_array_max_ulp(raw2[:, valid], raw[:, valid], maxulp=1)
    assert np.mean(raw2[:, valid] == raw[:, valid]) > 0.8
    assert np.all(raw2[:, ~valid] == -1.0)
    assert np.fromfile(out, "<i4", count=3).tolist() == [90, 90, 180]
    # Arbitrary values come back within 1 ulp.
    rng = np.random.default_rng(12)
    values = np.exp(rng.uniform(-10.0, 5.0, (*merl.SHAPE, 3)))
    values[~valid] = np.nan  # ignored in invalid cells
    back = merl.read(merl.write(tmp_path / "arb.binary", values, valid))
    np.testing.assert_array_equal(back.valid, valid)
    np.testing.assert_array_max_ulp(back.values[valid], values[valid], maxulp=1)
    # No temporary file left behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arb.binary", "copy.binary"]


def test_write_rejects_bad_input(tmp_path):
    p = tmp_path / "bad.binary"
    ok = np.ones((*merl.SHAPE, 3))
    with pytest.raises(ValueError, match="shape"):
        merl.write(p, ok[:-1])
    with pytest.raises(ValueError, match="valid"):
        merl.write(p, ok, np.ones(merl.SHAPE))  # float mask
    for bad, what in ((np.nan, "non-finite"), (np.inf, "non-finite"), (-0.5, "negative")):
        v = ok.copy()
        v[1, 2, 3, 0] = bad
        with pytest.raises(ValueError, match=what):
            merl.write(p, v)
    v = ok.copy()
    v[0, 0, 0] = 1e308
    with pytest.raises(ValueError, match="too large"):
        merl.write(p, v)
    assert not any(tmp_path.iterdir())  # nothing written, no temporary left


def test_write_replaces_atomically(tmp_path):
    p = tmp_path / "m.binary"
    p.write_bytes(b"old")
    p.chmod(0o640)
    merl.write(p, np.full((*merl.SHAPE, 3), 0.25))
    assert p.stat().st_mode & 0o777 == 0o640
    np.testing.assert_array_equal(merl.read(p).values, 0.25)
    assert [q.name for q in tmp_path.iterdir()] == ["m.binary"]


def _bad_files(tmp_path, raw):
    body = np.asarray(raw, "<f8").tobytes()
    header = np.asarray(merl.SHAPE, "<i4").tobytes()
    nan, inf = raw.copy(), raw.copy()
    nan[1, 2, 3, 4] = np.nan
    inf[2, 0, 0, 7] = -np.inf
    cases = {
        "empty": (b"", "shorter than the 12-byte header"),
        "short_header": (header[:7], "shorter than the 12-byte header"),
        "header_only": (header, "truncated"),
        "truncated": (header + body[:-8], "truncated"),
        "half": (header + body[: len(body) // 2 + 3], "truncated"),
        "oversized": (header + body + b"\0" * 8, "8 extra bytes"),
        "wrong_header": (np.asarray([90, 90, 360], "<i4").tobytes() + body, r"\(90, 90, 360\)"),
        "big_endian": (np.asarray(merl.SHAPE, ">i4").tobytes() + body, "big-endian"),
        "nan": (header + nan.astype("<f8").tobytes(), r"1 non-finite .* channel G .*\(2, 3, 4\)"),
        "inf": (header + inf.astype("<f8").tobytes(), r"1 non-finite .* channel B .*\(0, 0, 7\)"),
    }
    for name, (content, msg) in cases.items():
        path = tmp_path / f"{name}.binary"
        path.write_bytes(content)
        yield name, path, msg


def test_read_rejects_bad_files(tmp_path, raw_file):
    _, raw, _ = raw_file
    for name, path, msg in _bad_files(tmp_path, raw):
        with pytest.raises(merl.MerlFormatError, match=msg) as err:
            merl.read(path)
        assert str(err.value).startswith(str(path)), name
        assert err.value.__traceback__ is not None and isinstance(err.value, ValueError)


def test_read_missing_file(tmp_path):
    path = tmp_path / "nope.binary"
    with pytest.raises(FileNotFoundError, match="nope.binary") as err:
        merl.read(path)
    assert err.value.filename == str(path)


def test_merl_data_checks_and_immutability():
    valid = merl.valid_geometric()
    values = np.full((*merl.SHAPE, 3), 2.0)
    d = merl.MerlData(values, valid, name="x")
    assert np.all(d.values[~valid] == 0.0) and np.all(d.values[valid] == 2.0)
    assert values[~valid].min() == 2.0  # caller's array untouched
    with pytest.raises(ValueError, match="read-only"):
        d.values[0, 0, 0, 0] = 1.0
    with pytest.raises(AttributeError):
        d.name = "y"
    with pytest.raises(ValueError, match="shape"):
        merl.MerlData(values[:1], valid)
    with pytest.raises(ValueError, match="bool"):
        merl.MerlData(values, valid.astype(int))
    bad = values.copy()
    bad[0, 0, 0] = -1.0
    with pytest.raises(ValueError, match="negative"):
        merl.MerlData(bad, valid)
    with pytest.raises(ValueError, match="convention"):
        d.directions("middle")
    with pytest.raises(ValueError, match="convention"):
        d.angles("")


def test_from_function():
    def lambertian(wi, wo):
        return np.broadcast_to(np.array([0.1, 0.2, 0.3]) / np.pi, wi.shape)

    d = merl.from_function(lambertian, name="lamb")
    np.testing.assert_array_equal(d.valid, merl.valid_geometric("lower"))
    np.testing.assert_allclose(
        d.values[d.valid], np.tile([0.1, 0.2, 0.3], (d.valid.sum(), 1)) / np.pi
    )
    assert d.name == "lamb" and d.path is None
    # invalid_fraction: the geometric set plus the cells nearest grazing.
    d2 = merl.from_function(lambertian, invalid_fraction=0.242)
    assert round((1 - d2.valid_fraction) * merl.N_CELLS) == round(0.242 * merl.N_CELLS)
    assert np.all(d.valid[d2.valid])
    wi, wo = d.directions()
    dropped = d.valid & ~d2.valid
    kept_min = np.minimum(wi[..., 2], wo[..., 2])[d2.valid].min()
    assert np.minimum(wi[..., 2], wo[..., 2])[dropped].max() <= kept_min
    with pytest.raises(ValueError, match="invalid_fraction"):
        merl.from_function(lambertian, "centre", invalid_fraction=0.242)  # geometric: 0.248
    # Non-finite values where valid are an error; where invalid they are ignored.
    with pytest.raises(ValueError, match="non-finite"):
        merl.from_function(lambda wi, wo: np.full(wi.shape, np.nan))
    d3 = merl.from_function(lambda wi, wo: np.where(wi[..., 2:] > 0, 1.0, np.nan) * np.ones(3))
    assert np.all(d3.values[d3.valid] == 1.0)
    with pytest.raises(ValueError, match="shape"):
        merl.from_function(lambda wi, wo: wi[..., 0])


def test_written_file_gets_ordinary_permissions(tmp_path):
    """The temporary file of the atomic write is 0o600; the written file must not stay so."""
    import os

    values = np.zeros((90, 90, 180, 3))
    path = merl.write(tmp_path / "a.binary", values)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    os.chmod(path, 0o640)
    merl.write(path, values)  # replacing keeps the replaced file's permissions
    assert path.stat().st_mode & 0o777 == 0o640
