"""What a client sees of the server's JSON: free text with no server paths (`redact`, `REDACT`) and numbers
JSON can hold (`finite`), sent by `json_response`."""

from fastapi.responses import Response

from ..renderers.json_text import dumps, finite  # the one JSON writer's sanitiser (kept importable from here)
from ..renderers.redaction import PathRedactor


# --- no server paths in what a client sees -------------------------------------------------------

class Redactor:
    """The server's redaction of client-visible JSON: renderers.redaction.PathRedactor (the one path
    redactor: server folders - the data directory, repository, Python prefixes, working, temporary and home
    folders - and any absolute file path cut to base names) applied to the free-text fields only."""

    def __init__(self):
        self.paths = PathRedactor()

    def add(self, root) -> None:
        """Hide one more server folder (the data directory)."""
        self.paths.add(root)

    def text(self, value: str) -> str:
        return self.paths.text(value)

    def obj(self, obj, _free: bool = False):
        """A JSON-ready object with the free text redacted: the strings under a FREE_TEXT key (error
        messages, warnings, batch error messages, warm-up errors, at any depth). Identifiers (prim paths,
        camera and light usd_path, scene ids, file names) are the caller's own data and pass unchanged,
        even when they look like a server path (a prim `/tmp/Camera`)."""
        if isinstance(obj, str):
            return self.text(obj) if _free else obj
        if isinstance(obj, dict):
            return {(self.text(k) if _free and isinstance(k, str) else k):
                    self.obj(v, _free or (isinstance(k, str) and k in FREE_TEXT)) for k, v in obj.items()}
        if isinstance(obj, list):
            return [self.obj(v, _free) for v in obj]
        return obj


# the keys whose strings are free text a message writer may have put a server path in (only these are redacted)
FREE_TEXT = frozenset({"message", "warnings", "warning", "warm_errors", "note", "notes", "reasons"})


REDACT = Redactor()


def redact(text: str) -> str:
    """`text` with every server path cut to its file name (the one function every client message goes through)."""
    return REDACT.text(text)


# --- JSON output --------------------------------------------------------------------------------

def json_response(obj, status: int = 200, headers=None) -> Response:
    body = dumps(REDACT.obj(finite(obj)), separators=(",", ":"))
    return Response(body, status_code=status, media_type="application/json", headers=headers)
