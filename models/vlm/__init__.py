"""Contact-tolerance backends (DCT step 5): one interface (interface.py), run outside the tick."""
