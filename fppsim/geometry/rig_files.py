"""Rig calibration files: fppsim's JSON/YAML documents and OpenCV stereo calibrations.

:func:`read_rig_file` reads either as a rig document (the dictionary of ``Rig.to_dict``; ``Rig.load``
builds the rig from it), :func:`save_rig` writes a document (``Rig.save``), :func:`rig_from_opencv_stereo`
converts a ``cv2.stereoCalibrate`` result stored with ``cv2.FileStorage`` (YAML/XML) to a document, the
reference plane given by a board pose on it (:func:`rotation_to_plane_frame`) or a distance. The
geometry itself is :mod:`fppsim.geometry.rig`, which builds on this module (documents in, documents out: no
import of the rig here). :func:`checked_matrix` checks matrices read from files or given as numbers.
Units: mm.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from fppsim.errors import RigError
from fppsim.files import atomic_write_text, json_text

__all__ = ["checked_matrix", "read_rig_file", "save_rig", "rig_from_opencv_stereo", "rotation_to_plane_frame"]


def checked_matrix(value, shape, name: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (any nesting with that many numbers), all finite;
    :class:`RigError` naming ``name`` otherwise."""
    if isinstance(value, (dict, str, bytes)) or value is None:
        raise RigError(f"{name} must be {int(np.prod(shape))} numbers (shape {shape}), got {type(value).__name__}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{name} must be {int(np.prod(shape))} numbers (shape {shape}), got {value!r:.80}") from None
    if arr.size != int(np.prod(shape)):
        raise RigError(f"{name} must have {int(np.prod(shape))} numbers (shape {shape}), got shape {arr.shape}")
    arr = arr.reshape(shape)
    if not np.all(np.isfinite(arr)):
        raise RigError(f"{name} contains NaN or inf")
    return arr


def read_rig_file(path: str | os.PathLike) -> dict:
    """The rig document (``Rig.to_dict`` form) of a JSON/YAML file (fppsim format) or of an OpenCV
    FileStorage stereo calibration (:func:`rig_from_opencv_stereo`); RigError naming the file otherwise.
    ``Rig.load`` builds and checks the rig (errors then name the file too)."""
    path = Path(path)
    if not path.is_file():
        raise RigError(f"rig file not found: {path}")
    text = path.read_text(errors="replace")
    if text.lstrip().startswith("%YAML") or "opencv-matrix" in text or "<opencv_storage>" in text:
        return rig_from_opencv_stereo(path)
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml
            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except Exception as exc:  # json/yaml parse errors have long messages: keep the first line
        raise RigError(f"{path}: not valid JSON/YAML ({str(exc).splitlines()[0]})") from None
    return doc


def save_rig(doc: dict, path: str | os.PathLike) -> None:
    """Write a rig document (``Rig.to_dict``) as JSON or YAML (by the extension of ``path``), atomically."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml
        text = yaml.safe_dump(doc, sort_keys=False)
    else:
        text = json_text(doc, indent=2)
    atomic_write_text(path, text)


def rig_from_opencv_stereo(path: str | os.PathLike, plane_distance: float | None = None,
                           periods: float | None = None) -> dict:
    """The rig document (``Rig.to_dict`` form) of an OpenCV stereo calibration (cv2.FileStorage
    YAML/XML), camera = device 1.

    Recognised nodes (first match wins): camera matrix ``M1|K1|cameraMatrix1|camera_matrix``,
    distortion ``D1|dist1|distCoeffs1``, projector ``M2|K2|cameraMatrix2|projector_matrix``,
    ``D2|dist2|distCoeffs2``, and ``R``, ``T`` with ``X_proj = R X_cam + T`` (cv2.stereoCalibrate).
    Resolutions: ``camera_width/camera_height`` and ``projector_width/projector_height``, or
    ``image_width/image_height`` (camera) — default 640 x 352 and 912 x 1140.
    The reference plane: ``R_plane`` and ``T_plane`` (board-on-plane -> camera, as from solvePnP);
    without them the plane is perpendicular to the camera axis at ``plane_distance`` mm
    (node ``plane_distance``; required in that case).
    Fringe periods across the projector width: ``periods`` (argument, else node ``periods``, else 80).
    """
    import cv2  # optional heavy dependency (OpenCV)

    path = Path(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened()
    except (cv2.error, SystemError) as exc:  # a malformed document raises from inside OpenCV
        raise RigError(f"{path}: OpenCV cannot parse this FileStorage YAML/XML "
                       f"({str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__})") from None
    if not opened:
        raise RigError(f"{path}: OpenCV cannot read this file as FileStorage YAML/XML")

    def node(*names, required=True):
        for n in names:
            nd = fs.getNode(n)
            if not nd.empty():
                if nd.isMap() or nd.isSeq():
                    m = nd.mat()
                    if m is None:
                        raise RigError(f"{path}: node {n} is not a valid matrix (check rows x cols and data)")
                    return m
                if not (nd.isInt() or nd.isReal()):
                    raise RigError(f"{path}: node {n} must be a number, got {nd.string()!r}")
                return nd.real()
        if required:
            raise RigError(f"{path}: no node named {' or '.join(names)}")
        return None

    try:
        K1 = node("M1", "K1", "cameraMatrix1", "camera_matrix")
        D1 = node("D1", "dist1", "distCoeffs1", "camera_distortion", required=False)
        K2 = node("M2", "K2", "cameraMatrix2", "projector_matrix")
        D2 = node("D2", "dist2", "distCoeffs2", "projector_distortion", required=False)
        R = node("R")
        T = node("T")
        Rp = node("R_plane", "Rp", required=False)
        Tp = node("T_plane", "Tp", required=False)
        def size(default, *names):  # an explicit 0 must be refused, not replaced by the default
            v = node(*names, required=False)
            return default if v is None else v

        cw = size(640, "camera_width", "image_width")
        ch = size(352, "camera_height", "image_height")
        pw = size(912, "projector_width")
        ph = size(1140, "projector_height")
        if plane_distance is None:
            plane_distance = node("plane_distance", required=False)
        if periods is None:
            periods = node("periods", required=False)
    except cv2.error as exc:  # e.g. an opencv-matrix whose data count differs from rows x cols
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        detail = detail.split(" error: ", 1)[-1][:160]  # drop OpenCV's source path and line
        raise RigError(f"{path}: OpenCV cannot read a matrix node (data count must be rows x cols): {detail}") from None
    finally:
        fs.release()
    if R is None or T is None:
        raise RigError(f"{path}: R and T must be matrices")
    if R is not None and np.asarray(R).size == 3:  # Rodrigues vector
        R = cv2.Rodrigues(np.asarray(R, float))[0]
    if Rp is not None and np.asarray(Rp).size == 3:
        Rp = cv2.Rodrigues(np.asarray(Rp, float))[0]
    R = checked_matrix(R, (3, 3), "R")
    T = checked_matrix(T, (3,), "T")
    if Rp is not None and Tp is not None:
        Rw, tw = rotation_to_plane_frame(Rp, Tp)
    elif plane_distance:
        Rw, tw = np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, float(plane_distance)])
    else:
        raise RigError(f"{path}: no reference plane: add R_plane/T_plane or plane_distance (mm)")
    d1, d2 = _five_coefficients(D1, path, "camera"), _five_coefficients(D2, path, "projector")
    # checked and built by Rig.from_dict (errors: "camera: ...", "projector: ...", periods)
    return {"name": path.stem, "periods": 80.0 if periods is None else periods,
            "camera": {"K": K1, "dist": d1, "R": Rw, "t": tw, "width": cw, "height": ch},
            "projector": {"K": K2, "dist": d2, "R": R @ Rw, "t": R @ tw + T, "width": pw, "height": ph}}


def _five_coefficients(D, path, name) -> np.ndarray:
    """OpenCV distortion (4, 5, 8, 12 or 14 numbers) -> (k1, k2, p1, p2, k3); refuse models we cannot render."""
    d = np.zeros(5) if D is None else np.ravel(np.asarray(D, dtype=np.float64))
    if d.size > 5 and np.any(d[5:] != 0):
        raise RigError(f"{path}: {name} distortion has {d.size} coefficients with non-zero k4.. terms; "
                       "only (k1, k2, p1, p2, k3) is supported")
    out = np.zeros(5)
    out[: min(d.size, 5)] = d[:5]
    return out


def rotation_to_plane_frame(R_plane: np.ndarray, t_plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera extrinsics (R, t) for a world frame on a calibrated reference plane.

    ``R_plane, t_plane`` map plane-board coordinates to the camera frame (as from cv2.solvePnP on a
    board lying on the plane, the board's z = 0 being the plane). The result keeps the board's z = 0
    as the reference plane but flips the board frame (180 deg about x) if needed so that +z points
    towards the camera.
    """
    R = np.asarray(R_plane, float).reshape(3, 3)
    t = np.asarray(t_plane, float).reshape(3)
    cam_center = -R.T @ t
    if cam_center[2] < 0:
        flip = np.diag([1.0, -1.0, -1.0])
        R = R @ flip
    return R, t
