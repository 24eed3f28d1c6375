"""Fitting to real data: the rig's periods, baseline and depth scale, the optics, labelling real scans."""
