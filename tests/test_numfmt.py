"""The one number formatter (labbench.readout.numfmt): values to the digits their interval supports."""
import math

from hypothesis import given
from hypothesis import strategies as st

from labbench.readout.numfmt import EXACT, band_text, fmt, fmt_ci, plain
from labbench.readout.units import DisplayUnits


def test_value_to_the_digits_its_interval_supports():
    # the interval's half-width to two significant digits, the value to the same place
    assert fmt_ci(200.31234, 199.1, 201.52, "N/m") == "200.3 N/m (199.1 to 201.5)"
    assert fmt_ci(0.0942, 0.09, 0.0984, "kg") == "0.0942 kg (0.0900 to 0.0984)"
    assert fmt_ci(1.0, 0.5, 3.5) == "1.0 (0.5 to 3.5)"  # not centred: both ends, as always
    assert fmt_ci(524293.2, 524280, 524310) == "524293 (524280 to 524310)"
    assert fmt_ci(0.09999998, 0.09999979, 0.10000018, "N s/m") == \
        "0.09999998 N s/m (0.09999979 to 0.10000018)"


def test_an_interval_at_the_models_precision_is_not_twelve_digits():
    # issue 30: "0.0939999999962 +- 8.9e-12", "td 4.02e-10 (0 to 1.937e-09) ms"
    assert fmt_ci(0.0939999999962, 0.0939999999873, 0.0940000000051, "kg") == f"0.094 kg ({EXACT})"
    assert fmt_ci(4.02e-10, 0.0, 1.937e-09, "ms", scale=1.0) == f"0 ms ({EXACT})"
    assert fmt_ci(0.0, 0.0, 0.0) == f"0 ({EXACT})"


def test_no_interval_and_not_a_number():
    assert fmt_ci(0.0940007571, None, None, "kg") == "0.094 kg"
    assert fmt_ci(None) == "-" and fmt_ci(float("nan"), 0, 1) == "nan"
    assert fmt(None) == "-" and fmt(0.0940007571) == "0.094" and fmt(0.0940007571, 6) == "0.0940008"
    assert fmt([1.0, None]) == "[1, -]" and fmt(True) == "yes" and fmt(float("inf")) == "inf"


def test_scientific_only_where_plain_would_be_long_and_then_aligned():
    assert fmt_ci(3.2e9, 3.1e9, 3.3e9, "N") == "3.20e+09 N (3.10e+09 to 3.30e+09)"
    assert fmt_ci(1e-9, 0.5e-9, 1.5e-9, "s") == "1.00e-09 s (0.50e-09 to 1.50e-09)"


def test_bands_in_display_units():
    assert band_text((2.0, 3120.6)) == "2-3120 rad/s"
    assert band_text((0.3666, 100.0)) == "0.367-100 rad/s"
    assert band_text((2 * math.pi, 200 * math.pi), DisplayUnits(frequency="Hz")) == "1-100 Hz"
    assert plain(72.57) == "72.6" and plain(1e-5) == "0.00001"


@given(st.floats(-1e6, 1e6), st.floats(1e-6, 1e3), st.floats(1e-6, 1e3))
def test_the_written_interval_holds_the_value_and_reads_back_close(v, below, above):
    # every written number reads back within the resolution the text claims
    text = fmt_ci(v, v - below, v + above)
    if EXACT in text:
        assert max(below, above) <= 1e-6 * max(abs(v), abs(v - below), abs(v + above))
        return
    head, rest = text.split(" (")
    lo, hi = (float(x) for x in rest.rstrip(")").split(" to "))
    value = float(head)
    res = 10.0 ** (math.floor(math.log10(max(below, above))) - 1)
    assert abs(value - v) <= res / 2 * 1.0001 + 1e-9 * abs(v)
    assert lo <= value + res and value - res <= hi
    assert abs(lo - (v - below)) <= res / 2 * 1.0001 + 1e-9 * abs(v)


def test_frequencies_in_words_follow_the_display_units():
    # issue 43: a verdict's notes stayed in rad/s after the window switched to Hz
    from labbench.readout.numfmt import frequencies_in
    from labbench.readout.units import DisplayUnits

    hz = DisplayUnits(frequency="Hz")
    assert frequencies_in("drift at 2.3-17.6, 20.3-21.5 and 2 more rad/s; 2 rad/s needs 22 s", hz) \
        == "drift at 0.366-2.8, 3.23-3.42 and 2 more Hz; 0.318 Hz needs 22 s"
    assert frequencies_in("coherent frequencies between 1 and 1571 rad/s", hz) \
        == "coherent frequencies between 0.159 and 250 Hz"
    assert frequencies_in("outside: 100-3.14e+03 rad/s", hz) == "outside: 15.9-500 Hz"
    # words without a frequency, and every text in rad/s, stay as they are
    for text in ("chi2/dof 3.94e+12 > 4", "K = 200 N/m at 2 s", "drift at 2.3 rad/s"):
        assert frequencies_in(text) == text and frequencies_in(text, DisplayUnits()) == text
    assert frequencies_in("K = 200 N/m at 2 s", hz) == "K = 200 N/m at 2 s"
