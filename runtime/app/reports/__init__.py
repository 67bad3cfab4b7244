"""Reports from recorded runs: latency.py (figures), plots.py, html.py, cli.py (`dct report`)."""
