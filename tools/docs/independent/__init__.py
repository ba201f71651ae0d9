"""Independent re-computations of the papers' figures: numpy and scipy only, no hdhil.

One standalone module per paper figure (``python tools/docs/independent/NAME.py`` prints
its numbers); ``tools/docs/fidelity.py`` puts them beside the paper's and the project's.
"""
