"""Test helper: store a scene the way the server does (write_upload, then register_upload with its info in one
transaction, discard_upload when another request recorded the same bytes first)."""
from __future__ import annotations


def add_upload(store, tenant: str, data: bytes, filename: str, info: dict | None = None) -> tuple[str, bool]:
    """(scene_id, created): the same bytes again give the same id with created=False and leave no extra file."""
    scene_id, path, _ = store.write_upload(tenant, data, filename)
    created = store.register_upload(tenant, scene_id, path, len(data), {} if info is None else info)
    if not created:
        store.discard_upload(tenant, scene_id, path)
    return scene_id, created
