"""Contact detection on sampled strand polylines and against a head mesh.

detect.py: the ``Contacts`` record, segment/segment closest points, strand/strand contacts.
head.py:   ``HeadSurface`` (signed distance to a mesh), strand/head contacts, root gaps and snapping.
frames.py: orthonormal contact frames from normals.
Rules, defaults and measurements: docs/contact.md.
"""

from .detect import (DEFAULT_CONTACT_RADIUS, HEAD, Contacts, close_segment_pairs, detect_strand_contacts,
                     segment_closest_points)
from .frames import contact_frames
from .head import HeadSurface, as_head_surface, detect_head_contacts, root_gaps, snap_roots


def detect_contacts(points, offsets, arc, radius: float | None = None, *, head=None,
                    strand_strand: bool = True, head_radius: float | None = None,
                    stats: dict | None = None, progress=None) -> Contacts:
    """All contacts of the sampled strands: strand/strand (unless ``strand_strand`` is False), then
    strand/head when a ``head`` mesh (trimesh.Trimesh, (vertices, faces) or ``HeadSurface``) is given.

    radius: the contact radius r_c in metres (default ``DEFAULT_CONTACT_RADIUS``): strands touch
    when their axes are closer than 2 r_c, a strand touches the head when its axis is closer than
    ``head_radius`` (default r_c) to the surface or inside the head.
    progress: optional tqdm-like bar, advanced by one per pass (strand/strand, head) and told which.
    """
    radius = DEFAULT_CONTACT_RADIUS if radius is None else float(radius)
    head_radius = radius if head_radius is None else float(head_radius)

    def step(name):
        if progress is not None:
            progress.set_postfix_str(name)

    parts = []
    if strand_strand:
        step("strand/strand")
        parts.append(detect_strand_contacts(points, offsets, arc, radius, stats=stats))
        if progress is not None:
            progress.update(1)
    if head is not None:
        step("head")
        found = detect_head_contacts(points, offsets, arc, head, head_radius, stats=stats)
        found.radius = radius
        parts.append(found)
        if progress is not None:
            progress.update(1)
    out = Contacts.concatenate(parts)
    out.radius = radius
    return out


__all__ = [
    "DEFAULT_CONTACT_RADIUS", "HEAD", "Contacts", "HeadSurface", "as_head_surface", "close_segment_pairs",
    "contact_frames", "detect_contacts", "detect_head_contacts", "detect_strand_contacts", "root_gaps",
    "segment_closest_points", "snap_roots",
]
