"""Dataset I/O: the on-disk contract, codecs, readers of every layout, writers, and which rig goes with
the data (``rig_choice``)."""
