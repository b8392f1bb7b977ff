"""Server filesystem paths out of client-visible text: the one redactor the loader, the isolated loads
and the server use.

`PathRedactor(roots, hidden=...)`.text(s) rewrites, in this order of precedence (longest folder first):
- a path under one of `roots` (the scene's folder, an asset root): the root is dropped and the
  scene-relative rest kept (`<scene dir>/sub/x.usda` -> `sub/x.usda`; the root alone -> `.`);
- a path under one of the `hidden` server folders (by default the Python prefixes, i.e. the virtual
  environment, the repository, the working and temporary folders and the home folder; the server adds
  its data directory): cut to its base name (`<data>/scenes/<tenant>/<id>/x.usda` -> `x.usda`, so the
  storage layout does not show either; the folder alone -> its own base name);
- any other absolute path ending in a file name with a known extension: cut to its base name.
A folder matches only as a whole path component (`/tmp` does not match `/tmpfiles` nor `/var/tmp`), both as
given and resolved (symlinks), with an optional `file://` in front. A path ends at white space, quotes, `@`,
brackets, `,;:` (so `x.usda:3:26` keeps its line numbers and `a.usdz[inner/b.usda]` its entry).
Prim paths as USD writes them in messages (`</World/Mesh>`) are left alone, and so are paths without a known
file extension outside the folders (`/World/Mesh.points` is a property, not a file).
Anonymous layer identifiers (`anon:0x55a6175187e0:root.usda.checked.usda`: a heap address and the loader's
internal copy name) become the layer's readable name (`root.usda`; the loader's CHECKED_SUFFIX dropped; no
tag: `an anonymous layer`), and bare heap addresses USD prints (`<0x55a6175187e0>`, `0x55a6175187e0` of 9+
hex digits) become `<address>`: no process pointer reaches a client.
Redacting twice gives the same text as redacting once.
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
import threading

FILE_EXTENSIONS = (r"usd|usda|usdc|usdz|mtlx|abc|obj|vdb|so|dylib|dll|py|pyc|cpp|cc|h|hpp|json|txt|png|jpe?g"
                   r"|exr|hdr|tiff?|tx|osl|oso|glslfx|zip|sqlite|db|log|tmp")
_STOP = r"\s@'\"<>\[\](){},;:"  # characters that end a path in a message
_BEFORE = r"(?<![\w.<>/~-])"  # a path starts here (not inside a word, a prim path or another path)
_ABS_FILE = re.compile(_BEFORE + r"(?:file://)?(?:/[^" + _STOP + r"/]+)+\.(?:" + FILE_EXTENSIONS + r")\b")
CHECKED_SUFFIX = ".checked.usda"  # the loader's anonymous copies of checked layers are tagged <name> + this
_ANON = re.compile(r"anon:0x[0-9a-fA-F]+:([^\s@'\"<>\[\](){},;]*)")
_ADDRESS = re.compile(r"<0x[0-9a-fA-F]+>|(?<![\w])0x[0-9a-fA-F]{9,16}(?![\w])")
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def server_folders() -> list[str]:
    """The folders every redactor hides by default (those that exist in this process)."""
    out = [sys.prefix, sys.base_prefix, sys.exec_prefix, _REPO, tempfile.gettempdir(), os.path.expanduser("~")]
    try:
        out.append(os.getcwd())
    except OSError:  # the working folder was removed
        pass
    return out


class PathRedactor:
    """See the module docstring. `roots`: folders whose scene-relative rest is kept; `hidden`: folders cut
    to base names (None: `server_folders()`). `add()` registers one more folder later (thread-safe)."""

    def __init__(self, roots=(), *, hidden=None):
        self._lock = threading.Lock()
        self._folders: dict[str, bool] = {}  # folder -> relative (a root) or hidden
        self._pattern: re.Pattern | None = None
        for r in roots:
            if r:
                self._add(os.fspath(r), True)
        for h in server_folders() if hidden is None else hidden:
            if h:
                self._add(os.fspath(h), False)
        self._compile()

    def add(self, folder, *, relative: bool = False) -> None:
        with self._lock:
            self._add(os.fspath(folder), relative)
            self._compile()

    def _add(self, folder: str, relative: bool) -> None:
        forms = {os.path.abspath(folder), os.path.realpath(folder)}
        norm = os.path.normpath(folder)
        if not os.path.isabs(folder) and "/" in norm and not norm.startswith(".."):
            forms.add(norm)  # a relative folder also as given (a relative data directory)
        for v in forms:
            v = v.rstrip("/")
            # never "/" alone; a hidden folder one level below / ("/root", "/home") only for the temp dir
            depth = v.count("/") + (0 if os.path.isabs(v) else 1)
            if not v or depth < (1 if relative or v == tempfile.gettempdir().rstrip("/") else 2):
                continue
            if relative or v not in self._folders:  # a folder given as a root stays a root
                self._folders[v] = relative

    def _compile(self) -> None:
        if not self._folders:
            self._pattern = None
            return
        alternatives = "|".join(re.escape(d) for d in sorted(self._folders, key=len, reverse=True))
        self._pattern = re.compile(_BEFORE + r"(?:file://)?(" + alternatives + r")(?=[/" + _STOP + r"]|$)"
                                   r"(/[^" + _STOP + r"]*)?")

    def _sub(self, m) -> str:
        folder, rest = m.group(1), (m.group(2) or "").strip("/")
        if self._folders.get(folder):
            return rest or "."
        return os.path.basename(rest) if rest else (os.path.basename(folder) or "file")

    def text(self, s: str) -> str:
        if s and "0x" in s:
            s = _ANON.sub(_anon_name, s)
            s = _ADDRESS.sub("<address>", s)
        if not s or "/" not in s:
            return s
        pattern = self._pattern
        if pattern is not None:
            s = pattern.sub(self._sub, s)
        return _ABS_FILE.sub(lambda m: os.path.basename(m.group(0)), s)

    __call__ = text


def _anon_name(m) -> str:
    tag = m.group(1)
    while tag.endswith(CHECKED_SUFFIX):
        tag = tag[: -len(CHECKED_SUFFIX)]
    return tag or "an anonymous layer"
