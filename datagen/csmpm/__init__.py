"""CSMPM (thesis chapter 3): compressible gas on a regular grid (:mod:`.euler`, :mod:`.gas`)."""
