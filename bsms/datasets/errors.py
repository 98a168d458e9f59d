"""The one error for a source dataset file that cannot be used."""

from __future__ import annotations

__all__ = ["SourceError"]


class SourceError(ValueError):
    """A source dataset file (TFRecord, meta.json, authors' h5) that cannot be used; the message
    names the file, the record index and the field where they apply, and what to do."""

    def __init__(self, path, problem: str, *, record: int | None = None, field: str | None = None):
        where = str(path) + (f", record {record}" if record is not None else "") + (
            f", field '{field}'" if field is not None else "")
        super().__init__(f"{where}: {problem}")
        self.path, self.record, self.field = str(path), record, field
