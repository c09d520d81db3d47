"""The compiled fast-mode kernel against the NumPy path it replaces, on rendered frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scanner.core.images import load_laser_images
from scanner.stripe import fast, kernels, precise
from scanner.stripe.extract import StripeFlag, extract_stripe
from scanner.stripe.kernels import (
    HAVE_NUMBA,
    kth_smallest,
    line_peaks,
    saturated_centres,
    steger_points,
)
from scanner.virtual_cell.analytic import StripeSegment, render_stripes
from tests.conftest import real_data_subdir

pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed")

SHAPE = (240, 320)


def _frame(kind: str, width: int = SHAPE[1]):
    """A rendered frame of one kind, its saturation level and its half-window."""
    shape = (SHAPE[0], width)
    scale, dtype, hw = 1.0, np.uint8, 4
    segs = [StripeSegment((0, 240), (150.3, 0.21, -2e-4), amplitude=170.0)]
    if kind == "border":  # along the left border, then the right one
        segs = [
            StripeSegment((0, 120), (1.2, 0.01), amplitude=160.0),
            StripeSegment((120, 240), (width - 2.4, 0.0), amplitude=160.0),
            StripeSegment((0, 240), (150.0, 0.1), amplitude=60.0),
        ]
    elif kind == "saturated":
        segs = [
            StripeSegment((0, 240), (150.3, 0.21), amplitude=170.0),
            StripeSegment((60, 160), (80.0, 0.05), amplitude=900.0, sigma_px=2.0),
        ]
    elif kind == "uint16":
        scale, dtype = 64.0, np.uint16
        segs.append(StripeSegment((80, 120), (2.0, 0.0), amplitude=210.0))
        segs.append(StripeSegment((150, 200), (60.0, 0.0), amplitude=600.0))
    elif kind == "second":  # a second segment far away and one just outside the window
        segs += [
            StripeSegment((40, 200), (250.0, -0.1), amplitude=120.0),
            StripeSegment((100, 140), (160.0, 0.21), amplitude=110.0),
        ]
    elif kind == "dim":  # a stripe dimming along its length (low-contrast peaks)
        segs = [
            StripeSegment((0, 150), (150.3, 0.21, -2e-4), amplitude=170.0),
            StripeSegment((150, 240), (150.3, 0.21, -2e-4), amplitude=24.0),
        ]
    elif kind == "float32":  # grey levels that are not integers (rendered 16-bit, scaled)
        scale, dtype = 64.0, np.uint16
        segs.append(StripeSegment((80, 120), (2.0, 0.0), amplitude=210.0))
    elif kind == "double":  # two maxima inside one window
        segs = [
            StripeSegment((0, 240), (120.0, 0.0), amplitude=170.0, sigma_px=1.0),
            StripeSegment((100, 160), (124.5, 0.0), amplitude=150.0, sigma_px=1.0),
        ]
        hw = 6
    img, _ = render_stripes(
        shape,
        [StripeSegment(s.lines, s.coeffs, s.amplitude * scale, s.sigma_px) for s in segs],
        noise=2.0 * scale,
        background=8.0 * scale,
        seed=17,
        dtype=dtype,
        full_scale=255.0 * scale,
    )
    if kind == "float32":
        return img.astype(np.float32) / np.float32(scale * 1.37), 255.0 / 1.37, hw
    return img, 255.0 * scale, hw


KINDS = ["single", "border", "saturated", "uint16", "second", "double", "dim", "float32"]


def _numpy_primary(img, hw, sat, thr):
    """The NumPy path's primary peaks and lines with further candidates (as peaks.py), none
    of it compiled (as where numba cannot be imported)."""
    H = img.shape[0]
    cols = img.argmax(axis=1)
    if img.dtype == np.uint8:
        mask = cv2.threshold(img, min(thr, 254.0), 1, cv2.THRESH_BINARY)[1]
    else:
        mask = (img > thr).astype(np.uint8)
    with pytest.MonkeyPatch.context() as m:
        m.setattr(fast, "HAVE_NUMBA", False)
        prim = fast._measure_many(img, np.arange(H), cols, hw, sat, clear=mask)
    return prim, cols, mask.max(axis=1) > 0


def _assert_same_peaks(got, want):
    np.testing.assert_array_equal(got.line, want.line)
    np.testing.assert_array_equal(got.flags, want.flags)
    np.testing.assert_array_equal(got.peak, want.peak)
    np.testing.assert_allclose(got.pos, want.pos, rtol=0, atol=1e-4)
    np.testing.assert_allclose(got.width, want.width, rtol=0, atol=1e-3)
    scale = max(1.0, float(np.max(want.peak)) / 255.0)
    np.testing.assert_allclose(got.contrast, want.contrast, rtol=0, atol=1e-3 * scale)
    np.testing.assert_allclose(got.slope, want.slope, rtol=0, atol=1e-4 * scale)


@pytest.mark.parametrize("width", [320, 317])  # whole 8-pixel words per line, and not
@pytest.mark.parametrize("kind", KINDS)
def test_kernel_measures_the_primary_peaks_as_numpy_does(kind, width):
    img, sat, hw = _frame(kind, width)
    thr = 8.0 * sat / 255.0 + 0.1 * sat
    got = fast._measure_lines(img, hw, sat, thr)
    assert got is not None
    prim, cols, other = got
    want, want_cols, want_other = _numpy_primary(img, hw, sat, thr)
    np.testing.assert_array_equal(cols, want_cols)
    np.testing.assert_array_equal(other, want_other)
    _assert_same_peaks(prim, want)
    flags = np.bitwise_or.reduce(want.flags)
    if kind in ("border", "uint16"):
        assert flags & StripeFlag.BORDER
    if kind in ("saturated", "uint16"):
        assert flags & StripeFlag.SATURATED
    if kind == "double":
        assert flags & StripeFlag.AMBIGUOUS
    if kind == "second":
        assert np.count_nonzero(other) >= 150
    if kind == "float32":
        assert np.any(img != np.rint(img))


def test_kernel_finds_the_first_maximum_and_every_candidate_on_random_lines():
    rng = np.random.default_rng(18)
    for dtype, top in ((np.uint8, 6), (np.uint16, 6), (np.float32, 6)):
        for width in (64, 263, 520):
            img = rng.integers(0, top, size=(40, width)).astype(dtype)  # many ties
            hw, thr = 3, 3.5
            cols, *_, near, other = line_peaks(img, 1, hw, thr)
            np.testing.assert_array_equal(cols, img.argmax(axis=1))
            c = np.arange(width)
            outside = np.abs(c[None, :] - cols[:, None]) > hw
            np.testing.assert_array_equal(other, np.any((img > thr) & outside, axis=1))
            np.testing.assert_array_equal(near, (cols < hw + 2) | (cols > width - hw - 3))
            # Every third line, no candidate search.
            cols3, *_, other3 = line_peaks(img, 3, hw, np.inf)
            np.testing.assert_array_equal(cols3, img[::3].argmax(axis=1))
            assert not other3.any()


def test_kernel_level_between_integers_counts_as_numpy_compares():
    img = np.full((8, 64), 10, np.uint8)
    img[:, 30] = 200
    img[:3, 50] = 21
    for thr, want in ((20.0, 3), (20.99, 3), (21.0, 0), (254.5, 0)):
        assert np.count_nonzero(line_peaks(img, 1, 4, thr)[-1]) == want
    img[5, [2, 30]] = 255  # the first is the primary, the second still a candidate
    assert np.flatnonzero(line_peaks(img, 1, 4, 254.0)[-1]).tolist() == [5]
    with pytest.raises(ValueError, match="thr"):
        line_peaks(img, 1, 4, -1.0)


def _same_lines(got, want):
    """Two line_peaks results: the same peaks, candidates and border marks; the same measures."""
    for k in (0, 2, 6, 7):  # cols, peak, near, other
        np.testing.assert_array_equal(got[k], want[k])
    near = want[6]
    for g, w in zip(got[1:6], want[1:6], strict=True):  # pos, peak, contrast, slope, width
        np.testing.assert_allclose(g[~near], w[~near], rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_column_kernel_reads_a_transposed_view_as_the_row_kernel_reads_its_copy(kind):
    img, sat, hw = _frame(kind)
    view = np.ascontiguousarray(img.T).T  # the same frame, its scan lines stored as columns
    assert view.flags.f_contiguous and not view.flags.c_contiguous
    thr = 8.0 * sat / 255.0 + 0.1 * sat
    for step in (1, 3):
        _same_lines(line_peaks(view, step, hw, thr), line_peaks(img, step, hw, thr))
    prim, cols, other = fast._measure_lines(view, hw, sat, thr)
    want, want_cols, want_other = _numpy_primary(img, hw, sat, thr)
    np.testing.assert_array_equal(cols, want_cols)
    np.testing.assert_array_equal(other, want_other)
    _assert_same_peaks(prim, want)


def test_column_kernel_on_random_frames_with_long_lines_and_ties():
    # Lines longer than the kernel's 255-row blocks, and many equal maxima: the first one,
    # as the row kernel (and argmax) finds it, whichever block it falls in.
    rng = np.random.default_rng(23)
    for dtype, top in ((np.uint8, 6), (np.uint8, 256), (np.uint16, 6), (np.float32, 6)):
        for length in (40, 255, 256, 700):
            img = rng.integers(0, top, size=(37, length)).astype(dtype)
            view = np.ascontiguousarray(img.T).T
            for step, thr in ((1, 3.5), (2, 3.5), (1, np.inf)):
                _same_lines(line_peaks(view, step, 3, thr), line_peaks(img, step, 3, thr))
            np.testing.assert_array_equal(line_peaks(view, 1, 3, 3.5)[0], img.argmax(axis=1))


@pytest.mark.parametrize("kind", KINDS)
def test_steger_kernel_reads_a_transposed_view(kind):
    img, sat, hw = _frame(kind)
    view = np.ascontiguousarray(img.T).T
    prim = fast._measure_lines(img, hw, sat)[0]
    saturated = (prim.flags & np.uint8(StripeFlag.SATURATED)) != 0
    level = prim.peak - prim.contrast
    args = (prim.line, prim.pos, prim.slope, level, saturated, 1.5)
    np.testing.assert_allclose(steger_points(view, *args), steger_points(img, *args), atol=1e-9)


def test_column_scan_lines_give_the_profile_of_the_transposed_frame():
    # A frame whose stripe runs left to right, scanned by columns in place, against the same
    # frame transposed and scanned by rows: the same points with u and v swapped.
    for kind in KINDS:
        img, _, _ = _frame(kind)
        for mode in ("fast", "precise"):
            got = extract_stripe(np.ascontiguousarray(img.T), mode=mode, orientation="cols")
            want = extract_stripe(img, mode=mode, orientation="rows")
            np.testing.assert_array_equal(got.line, want.line)
            np.testing.assert_array_equal(got.flags, want.flags)
            np.testing.assert_allclose(got.u, want.v, rtol=0, atol=1e-6)
            np.testing.assert_allclose(got.v, want.u, rtol=0, atol=1e-6)


@pytest.fixture
def numpy_path(monkeypatch):
    """Run the extractor without the kernel (as where numba cannot be imported)."""

    def run(*args, **kwargs):
        with monkeypatch.context() as m:
            m.setattr(fast, "HAVE_NUMBA", False)
            m.setattr(precise, "HAVE_NUMBA", False)
            m.setattr(kernels, "HAVE_NUMBA", False)
            return extract_stripe(*args, **kwargs)

    return run


@pytest.mark.parametrize("orientation", ["rows", "cols"])
@pytest.mark.parametrize("kind", KINDS)
def test_extract_stripe_gives_the_numpy_profile(kind, orientation, numpy_path):
    img, _, _ = _frame(kind)
    if orientation == "cols":
        img = np.ascontiguousarray(img.T)
    for mode in ("fast", "precise"):
        got = extract_stripe(img, mode=mode, orientation=orientation)
        want = numpy_path(img, mode=mode, orientation=orientation)
        np.testing.assert_array_equal(got.line, want.line)
        np.testing.assert_array_equal(got.flags, want.flags)
        np.testing.assert_array_equal(got.intensity, want.intensity)
        np.testing.assert_allclose(got.u, want.u, rtol=0, atol=1e-4)
        np.testing.assert_allclose(got.v, want.v, rtol=0, atol=1e-4)
        np.testing.assert_allclose(got.width_px, want.width_px, rtol=0, atol=1e-3)
        if kind == "dim":
            assert np.count_nonzero(want.flags & StripeFlag.LOW_CONTRAST) > 50


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.7])
@pytest.mark.parametrize("kind", KINDS)
def test_steger_kernel_refines_as_numpy_does(kind, sigma):
    img, sat, hw = _frame(kind)
    prim = fast._measure_lines(img, hw, sat)[0]
    saturated = (prim.flags & np.uint8(StripeFlag.SATURATED)) != 0
    level = prim.peak - prim.contrast
    got = steger_points(img, prim.line, prim.pos, prim.slope, level, saturated, sigma)
    want, _ = precise._refine_numpy(img, prim, sigma, saturated, level.astype(np.float64))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)
    # The refinement moved the centres whose patch is inside the image (not only kept the
    # fast ones); saturated ones and those at the border keep theirs.
    R = int(np.ceil(2.5 * sigma))
    c0 = np.rint(prim.pos)
    inside = (c0 >= R) & (c0 < img.shape[1] - R)
    moved = np.abs(got - prim.pos) > 1e-6
    if kind != "border":  # (there the primary peaks all lie at the border)
        assert np.mean(moved[inside & ~saturated]) > 0.5
    assert not moved[saturated | ~inside].any()


def test_steger_kernel_refuses_what_it_cannot_refine():
    z = np.zeros(3)
    with pytest.raises(ValueError, match="sigma"):
        steger_points(np.zeros((8, 40), np.uint8), z.astype(int), z, z, z, z.astype(bool), 0.0)
    with pytest.raises(ValueError, match="native"):
        steger_points(np.zeros((8, 40)), z.astype(int), z, z, z, z.astype(bool), 1.5)


def test_float_frames_with_nan_keep_the_numpy_path(numpy_path):
    img, _, _ = _frame("single")
    f = img.astype(np.float32)
    assert fast._measure_lines(f, 4, np.inf, 30.0) is not None
    f[10, 5] = np.nan
    assert fast._measure_lines(f, 4, np.inf, 30.0) is None
    f[51, 160:163] = np.nan  # inside the precise mode's patch around row 50's centre
    for mode in ("fast", "precise"):
        got = extract_stripe(f, mode=mode, orientation="rows", noise=2.0)
        want = numpy_path(f, mode=mode, orientation="rows", noise=2.0)
        np.testing.assert_array_equal(got.u, want.u)
        np.testing.assert_array_equal(got.v, want.v)


def test_auto_half_window_is_the_numpy_one(monkeypatch):
    from scanner.stripe.estimates import auto_half_window

    rng = np.random.default_rng(19)
    for sigma in (1.0, 1.7, 2.6):
        seg = StripeSegment((0, 240), (rng.uniform(20, 300), 0.2), amplitude=170.0, sigma_px=sigma)
        img, _ = render_stripes(SHAPE, [seg], noise=1.0, seed=int(rng.integers(1000)))
        got = auto_half_window(img, 1.0)
        with monkeypatch.context() as m:
            m.setattr(fast, "HAVE_NUMBA", False)
            assert auto_half_window(img, 1.0) == got


@pytest.mark.parametrize(
    "frame,hw,step,reason",
    [
        (np.zeros((4, 40), ">u2"), 3, 1, "native"),
        (np.zeros((4, 40), np.float64), 3, 1, "native"),
        (np.zeros((4, 10), np.uint8), 3, 1, "columns"),
        (np.zeros((4, 10), np.uint8).T, 3, 1, "columns"),
        (np.zeros((8, 80), np.uint8)[::2, ::2], 3, 1, "neither C- nor F-contiguous"),
        (np.zeros((2, 4, 40), np.uint8), 3, 1, "2-D"),
        (np.zeros((4, 40), np.uint8), 0, 1, "hw, step"),
        (np.zeros((4, 40), np.uint8), 3, 0, "hw, step"),
    ],
)
def test_line_peaks_refuses_what_the_kernel_cannot_read(frame, hw, step, reason) -> None:
    with pytest.raises(ValueError, match=reason):
        line_peaks(frame, step, hw, 10.0)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_kth_smallest_is_numpys_partition(dtype):
    rng = np.random.default_rng(11)
    # (the compiled function's own Python, as where numba is missing, on a few of them)
    py = getattr(kernels._kth_smallest, "py_func", kernels._kth_smallest)
    for trial in range(2000):
        n = int(rng.integers(1, 1500))
        if trial % 3:
            values = np.abs(rng.normal(60.0, 20.0, n)).astype(dtype)
        else:  # many ties
            values = rng.integers(0, 4, n).astype(dtype)
        if values.dtype.kind == "f" and trial % 5 == 0:
            values[rng.random(n) < 0.3] = np.nan  # NaN sorts last
        k = int(rng.integers(0, n))
        want = float(np.partition(values, k)[k])
        got = [kth_smallest(values, k)] + ([float(py(values, k))] if trial < 100 else [])
        for g in got:
            assert g == want or (np.isnan(g) and np.isnan(want)), (trial, n, k, g, want)


def test_kth_smallest_refuses_k_outside_the_values():
    with pytest.raises(ValueError, match="k: expected 0 <= k < 3, got 3"):
        kth_smallest(np.zeros(3, np.float32), 3)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_saturated_centres_kernel_is_the_numpy_reference(dtype):
    """Clipped Gaussian lines of random centre, width and height, some cut by the border, some
    flat-topped over one flank only, read from a frame and from its transposed view."""
    rng = np.random.default_rng(23)
    full = 255.0 if dtype == np.uint8 else 4095.0
    n, width = 400, 96
    u = np.arange(width)
    centre = rng.uniform(-3.0, width + 3.0, n)
    sigma = rng.uniform(0.8, 6.0, n)
    height = full * rng.uniform(1.05, 8.0, n)
    profile = height[:, None] * np.exp(-0.5 * ((u - centre[:, None]) / sigma[:, None]) ** 2)
    profile += rng.uniform(0.0, 0.1, n)[:, None] * full * (u / width)  # a sloping background
    profile += rng.normal(0.0, 0.004 * full, profile.shape)
    img = np.clip(np.rint(profile), 0, full).astype(dtype)
    sat = float(img.max())
    lines = np.arange(n)
    shift = np.where(rng.random(n) < 0.25, rng.integers(-12, 13, n), 0)  # some beside the run
    near = np.clip(np.rint(centre) + shift, 0, width - 1).astype(np.int64)
    on_run = np.where(img[lines, near] >= sat, near, img.argmax(axis=1))
    for cols, level in ((on_run, sat), (near, sat - 0.5), (near, sat)):
        want_pos, want_run = fast._saturated_centres(img, lines, cols, level)
        for frame in (img, np.ascontiguousarray(img.T).T):
            got_pos, got_run = saturated_centres(frame, lines, cols, level)
            np.testing.assert_array_equal(got_run, want_run)
            np.testing.assert_allclose(got_pos, want_pos, rtol=0, atol=1e-9)
        refined = np.abs(want_pos - np.round(want_pos * 2) / 2) > 1e-6
        assert np.count_nonzero(refined) > n // 3  # the flanks' fit moved most centres
    assert np.count_nonzero(img[lines, near] < sat) > 30  # peak pixels off the run tried


def test_windows_whose_width_is_undefined_on_most_lines_are_chosen_as_numpy_does(numpy_path):
    """Minus infinity in a flank pixel of most lines gives those windows no width: the median
    width is then NaN, which is not the same as no window inside the image."""
    img, _, hw = _frame("single")
    f = img.astype(np.float32)
    cols = f.argmax(axis=1)
    f[np.arange(200), cols[:200] + hw + 2] = -np.inf
    with np.errstate(invalid="ignore"):
        got = extract_stripe(f, mode="fast", orientation="rows", noise=2.0, half_window_px=hw)
        want = numpy_path(f, mode="fast", orientation="rows", noise=2.0, half_window_px=hw)
    assert want.line.size == 240
    np.testing.assert_array_equal(got.line, want.line)
    np.testing.assert_array_equal(got.flags, want.flags)
    np.testing.assert_allclose(got.u, want.u, rtol=0, atol=1e-4)


def test_real_laser_frames_give_the_numpy_profile(numpy_path):
    """Real captures (a line laser over a lit scene, JPEG, saturated runs on paper nearly as
    bright as the clip level) are extracted alike by the compiled and the NumPy paths: the
    same lines and flags, centres within 1e-3 px (float32 sums against float64). A saturated
    run whose flanks are all at one level has no vertex in either path."""
    root = real_data_subdir("zhaocongyang_linelight")
    frames = sorted((root / "light_picture").glob("*.jpg"))
    assert frames
    saturated = 0
    for path in frames:
        img, _ = load_laser_images(path)
        for mode in ("fast", "precise"):
            got = extract_stripe(img, mode=mode)
            want = numpy_path(img, mode=mode)
            np.testing.assert_array_equal(got.line, want.line)
            np.testing.assert_array_equal(got.flags, want.flags)
            np.testing.assert_allclose(got.u, want.u, rtol=0, atol=1e-3)
            np.testing.assert_allclose(got.v, want.v, rtol=0, atol=1e-3)
            saturated += np.count_nonzero(got.flags & StripeFlag.SATURATED)
    assert saturated > 1000
