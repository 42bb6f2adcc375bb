"""The field layout of a ROS 2 message from its ``ros2idl`` schema (the OMG IDL subset rosidl writes).

rosbag2 writes the schema of a type defined in IDL (or of any type, with some bridges) as IDL text: the
top-level type's IDL, then each dependency after a line of ``=`` and ``IDL: pkg/msg/Name``. Its CDR bytes
are the same as for the equivalent ``.msg`` definition, so a schema whose flattened layout
(`idl_layout`) equals a standard type's (`pipeline.logs.cdr.schema_layout`) is decoded as that type.
"""

from __future__ import annotations

import re

_PRIMITIVES = {
    "double": "float64",
    "float": "float32",
    "short": "int16",
    "unsigned short": "uint16",
    "long": "int32",
    "unsigned long": "uint32",
    "long long": "int64",
    "unsigned long long": "uint64",
    "boolean": "bool",
    "octet": "byte",
    "char": "char",
    "string": "string",
    "wstring": "wstring",
    **{f"{s}int{n}": f"{s}int{n}" for s in ("", "u") for n in (8, 16, 32, 64)},
}
_TOKEN = re.compile(r"[A-Za-z_][\w]*(?:::[A-Za-z_]\w*)*|\d+|[{}<>\[\];,=]")


def _clean(text: str) -> str:
    """IDL text without comments, string literals, preprocessor lines and annotations."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.DOTALL)
    text = re.sub(r"//[^\n]*", " ", text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    text = re.sub(r"^\s*#[^\n]*", " ", text, flags=re.MULTILINE)
    text = re.sub(r"^\s*(?:={3,}|IDL:[^\n]*)\s*$", " ", text, flags=re.MULTILINE)
    while True:  # annotations, possibly with nested parentheses
        stripped = re.sub(r"@\w+(\s*\([^()]*\))?", " ", text)
        if stripped == text:
            return text
        text = stripped


def _key(scoped: str, modules: list[str]) -> str:
    """'pkg::msg::Name' or 'Name' (in the current modules) -> 'pkg/Name'."""
    parts = scoped.split("::") if "::" in scoped else [*modules, scoped]
    return f"{parts[0]}/{parts[-1]}"


def _type(tokens: list[str], i: int) -> tuple[str, str, int]:
    """(base type, suffix, next index) of the type starting at tokens[i]."""
    if tokens[i] == "sequence":  # sequence < T [, N] >
        base, _, j = _type(tokens, i + 2)
        if tokens[j] == ",":
            return base, f"[<={tokens[j + 1]}]", j + 3
        return base, "[]", j + 1
    for words in (3, 2):
        name = " ".join(tokens[i : i + words])
        if name in _PRIMITIVES:
            return _PRIMITIVES[name], "", i + words
    if tokens[i] in ("string", "wstring") and i + 1 < len(tokens) and tokens[i + 1] == "<":
        return f"{tokens[i]}<={tokens[i + 2]}", "", i + 4
    if tokens[i] in _PRIMITIVES:
        return _PRIMITIVES[tokens[i]], "", i + 1
    return tokens[i], "", i + 1  # a (scoped) type name


def _parse(text: str) -> dict[str, list[tuple[str, str, str]]]:
    """Every struct of the IDL text: 'pkg/Name' -> [(primitive or scoped type, array suffix, field name)]."""
    tokens = _TOKEN.findall(_clean(text))
    structs: dict[str, list[tuple[str, str, str]]] = {}
    typedefs: dict[str, tuple[str, str]] = {}
    modules: list[str] = []
    current: list[tuple[str, str, str]] | None = None
    i = 0
    while i < len(tokens):
        t = tokens[i]
        if t == "module" and current is None:
            modules.append(tokens[i + 1])
            i += 3
        elif t == "struct" and current is None:
            current = structs.setdefault(_key(tokens[i + 1], modules), [])
            i += 3
        elif t == "}":
            if current is not None:
                current = None
            elif modules:
                modules.pop()
            i += 2 if i + 1 < len(tokens) and tokens[i + 1] == ";" else 1
        elif t == "const":
            while tokens[i] != ";":
                i += 1
            i += 1
        elif t == "typedef" or current is not None:
            base, suffix, j = _type(tokens, i + 1 if t == "typedef" else i)
            name = tokens[j]
            if tokens[j + 1] == "[":
                suffix, j = f"[{tokens[j + 2]}]", j + 3
            if base in typedefs:
                base, suffix = typedefs[base][0], typedefs[base][1] + suffix
            if t == "typedef":
                typedefs[name] = (base, suffix)
            else:
                current.append((base, suffix, name))
            i = j + 2
        else:
            i += 1
    return structs


def idl_layout(name: str, text: str) -> tuple[tuple[str, str], ...] | None:
    """The flattened field list ((dotted field path, primitive type[suffix]), ...) of a ros2idl schema.

    Same form as `pipeline.logs.cdr.schema_layout`; None if the text cannot be read or a nested type is
    not defined in it.
    """
    try:
        structs = _parse(text)
    except IndexError:
        return None
    structs.setdefault("builtin_interfaces/Time", [("int32", "", "sec"), ("uint32", "", "nanosec")])

    def flatten(key: str, prefix: str, depth: int) -> list[tuple[str, str]] | None:
        if key not in structs or depth > 16:
            return None
        out: list[tuple[str, str]] = []
        for base, suffix, fname in structs[key]:
            if base in _PRIMITIVES.values() or base.startswith(("string<=", "wstring<=")):
                out.append((prefix + fname, base + suffix))
                continue
            nested_key = _key(base, key.split("/")[:1] + ["msg"])
            if suffix:
                out.append((prefix + fname, nested_key + suffix))
                continue
            nested = flatten(nested_key, f"{prefix}{fname}.", depth + 1)
            if nested is None:
                return None
            out.extend(nested)
        return out

    result = flatten(_key(name.replace("/", "::"), []), "", 0)
    return tuple(result) if result else None
