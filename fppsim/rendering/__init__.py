"""Scenes and rendering: meshes, poses, depth renders, the optics stage, one sample's images."""
