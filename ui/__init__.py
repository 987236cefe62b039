"""forestreg.ui: the PySide6 + pyvista desktop GUI over the engine's project model (issue 4).

Nothing here may be imported by the engine; this package imports Qt lazily inside its modules.
"""
