"""File formats. One module owns each format, with symmetric load/save functions.

The written spec of every format is data/README.md.
"""
