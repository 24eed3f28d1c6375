"""Dataset I/O: the on-disk contract, codecs, readers, writers and safe file handling."""
