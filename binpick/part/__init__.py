"""A part from its CAD file: the mesh read and checked for its unit and size (ingest, scale), and
the part model sampled from it (model)."""
