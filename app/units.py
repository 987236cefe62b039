"""The files' units: metres per unit of each ``--units`` choice (no heavy import: the command
line's parser reads it before anything else loads)."""

#: Metres per unit of the files' coordinates (the ``--units`` choices).
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "usft": 1200.0 / 3937.0}
