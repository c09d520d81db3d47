"""Scan-to-CAD inspection: align a cloud to a nominal mesh without a starting guess, then the
signed deviation of every point, judged on tolerance bands per region (contract section 5).

``spec`` (the TOML spec), ``surface`` (the nominal surface: closest points, signed distances),
``align`` (global search, robust best-fit, RPS), ``inspect`` (the whole inspection),
``result`` (what it returns), ``sections`` and ``report`` (the HTML report).
"""
