"""``jurs.fit`` and what surrounds it: automatic settings, compilation, fits over several
devices or processes, and fits run in chunks."""
