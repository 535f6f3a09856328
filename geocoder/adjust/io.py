"""Plain-file formats of the block adjustment (documented in the README).

- points CSV: ``id,role,X,Y,Z,sigma_X,sigma_Y,sigma_Z`` — ECEF metres; role ``control``,
  ``tie`` or ``check``; an empty or ``inf`` sigma leaves the coordinate free.
- observations CSV: ``frame,point,x,y,w_xx,w_xy,w_yy`` — image column/row of point ``point``
  in frame ``frame`` (the frame's index in the frames file) and the symmetric 2x2 weight
  (an edge point's weight is singular; it is never inverted).
- frames JSON: ``{"frames": [{"id": ..., "model": "polynomial" | "linescanner" | "rpc", ...}]}``
  with, per model, ``order, origin_lat, origin_lon, scale`` (polynomial), ``scanner`` (the
  LineScanner fields) and ``free`` (a parameter-set name or a 32-long list of
  booleans) and optional ``prior_sigma`` (linescanner), or the RPC00B fields under ``rpc``;
  ``params`` (optional start values) for any model.

Every writer writes its file whole (:func:`write_text`): a failure leaves an earlier file intact.
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import asdict

import numpy as np

from ..errors import InputError
from ..storage import remove, temporary_sibling
from .linescanner_geometry import LineScanner
from .models import RPC, LineScannerModel, Polynomial2D, RPCModel
from .observations import GroundPoints, ImageObservations
from .orbit import Orbit
from .problem import Frame

POINT_FIELDS = ["id", "role", "X", "Y", "Z", "sigma_X", "sigma_Y", "sigma_Z"]
OBS_FIELDS = ["frame", "point", "x", "y", "w_xx", "w_xy", "w_yy"]


def _rows(path: str, fields: list[str]) -> list[dict]:
    if not os.path.exists(path):
        raise InputError(path, "no such file")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [k for k in fields if k not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, f"missing column(s) {missing}; expected {fields}")
        return list(reader)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write a whole text file atomically: readers see the old file or the new one, never a part.

    The text goes into a hidden sibling (:func:`geocoder.storage.temporary_sibling`) that
    replaces ``path`` (``os.replace``) only when written and closed; on any failure the
    sibling is removed and an earlier ``path`` is left as it was.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write (a local path).
    text : str
        Its whole content (UTF-8; newlines written as given).
    """
    final = os.fspath(path)
    tmp = temporary_sibling(final)
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, final)
    except BaseException:
        remove(tmp)
        raise


def _csv_text(header: list[str], rows) -> str:
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def _float(v: str) -> float:
    return float(v) if v not in ("", None) else float("inf")


def read_points(path: str) -> GroundPoints:
    rows = _rows(path, POINT_FIELDS)
    try:
        xyz = np.array([[float(r["X"]), float(r["Y"]), float(r["Z"])] for r in rows])
        sigma = np.array([[_float(r["sigma_X"]), _float(r["sigma_Y"]), _float(r["sigma_Z"])] for r in rows])
        ids = np.array([int(r["id"]) for r in rows], dtype=np.int64)
    except ValueError as exc:
        raise InputError(path, f"bad number ({exc})") from None
    role = np.array([r["role"] for r in rows])
    return GroundPoints(id=ids, X=xyz[:, 0], Y=xyz[:, 1], Z=xyz[:, 2], role=role, true_X=xyz[:, 0],
                        true_Y=xyz[:, 1], true_Z=xyz[:, 2], sigma=sigma)


def write_points(path: str, points: GroundPoints, xyz: np.ndarray | None = None) -> None:
    xyz = points.xyz if xyz is None else xyz
    rows = ([int(points.id[i]), points.role[i], *(f"{v:.4f}" for v in xyz[i]), *points.sigma[i]]
            for i in range(len(points)))
    write_text(path, _csv_text(POINT_FIELDS, rows))


def read_observations(path: str) -> ImageObservations:
    rows = _rows(path, OBS_FIELDS)
    try:
        a = np.array([[float(r[k]) for k in OBS_FIELDS] for r in rows]).reshape(-1, len(OBS_FIELDS))
    except ValueError as exc:
        raise InputError(path, f"bad number ({exc})") from None
    weight = np.stack([np.stack([a[:, 4], a[:, 5]], 1), np.stack([a[:, 5], a[:, 6]], 1)], 1)
    return ImageObservations(frame=a[:, 0].astype(np.int64), point=a[:, 1].astype(np.int64), row=a[:, 3], col=a[:, 2],
                             true_row=a[:, 3], true_col=a[:, 2], weight=weight, kind=np.full(len(a), "point"),
                             theta=np.full(len(a), np.nan))


def write_observations(path: str, obs: ImageObservations) -> None:
    W = obs.weight
    rows = ([int(obs.frame[i]), int(obs.point[i]), f"{obs.col[i]:.4f}", f"{obs.row[i]:.4f}", W[i, 0, 0], W[i, 0, 1],
             W[i, 1, 1]] for i in range(len(obs)))
    write_text(path, _csv_text(OBS_FIELDS, rows))


def scanner_to_dict(s: LineScanner) -> dict:
    return {"orbit": asdict(s.orbit), "rows": s.rows, "cols": s.cols, "ifov": s.ifov, "kind": s.kind,
            "col_time": s.col_time, "deviations": np.asarray(s.deviations).tolist()}


def scanner_from_dict(d: dict) -> LineScanner:
    return LineScanner(orbit=Orbit(**d["orbit"]), rows=d["rows"], cols=d["cols"], ifov=d["ifov"], kind=d["kind"],
                       col_time=d.get("col_time", 0.0), deviations=np.asarray(d["deviations"], dtype=np.float64))


def frame_from_dict(d: dict, path: str = "frames") -> Frame:
    kind = d.get("model")
    if kind == "polynomial":
        model = Polynomial2D(int(d["order"]), float(d["origin_lat"]), float(d["origin_lon"]), float(d.get("scale", 1e5)))
    elif kind == "linescanner":
        free = d.get("free", "full")
        mask = LineScannerModel.parameter_sets()[free] if isinstance(free, str) else np.asarray(free, dtype=bool)
        model = LineScannerModel(scanner_from_dict(d["scanner"]), mask)
    elif kind == "rpc":
        model = RPCModel(RPC(**{k: (np.asarray(v) if isinstance(v, list) else v) for k, v in d["rpc"].items()}))
    else:
        raise InputError(path, f"frame {d.get('id')!r}: unknown model {kind!r} (polynomial, linescanner or rpc)")
    params = np.asarray(d["params"], dtype=np.float64) if "params" in d else model.initial_params()
    prior = None
    if "prior_sigma" in d:
        prior = np.diag(1.0 / np.asarray(d["prior_sigma"], dtype=np.float64) ** 2)
    return Frame(model=model, params=params, prior_weight=prior)


def read_frames(path: str) -> tuple[list[Frame], list[dict]]:
    if not os.path.exists(path):
        raise InputError(path, "no such file")
    try:
        with open(path) as f:
            doc = json.load(f)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    specs = doc.get("frames") if isinstance(doc, dict) else None
    if not specs:
        raise InputError(path, "expected {\"frames\": [...]} with at least one frame")
    return [frame_from_dict(d, path) for d in specs], specs


def write_frames(path: str, specs: list[dict], params: list[np.ndarray], covariances: list | None = None) -> None:
    out = []
    for k, d in enumerate(specs):
        e = dict(d)
        e["params"] = np.asarray(params[k]).tolist()
        if covariances is not None and covariances[k] is not None:
            e["param_sigma"] = np.sqrt(np.abs(np.diag(covariances[k]))).tolist()
        out.append(e)
    write_text(path, json.dumps({"frames": out}, indent=1))
