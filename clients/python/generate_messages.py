#!/usr/bin/env python3
"""Generates egoslam_client.messages from proto/egoslam/v1 (the public client contract:
geometry and map; not the internal package egoslam.internal.v1) with protoc, and
rewrites the generated imports to the package's own path so that no top-level `egoslam`
package is needed. The output is committed, so installing the client needs no protoc.

    python3 clients/python/generate_messages.py           # regenerate
    python3 clients/python/generate_messages.py --check   # exit 1 if the committed files are stale
"""
import argparse
import pathlib
import re
import subprocess
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parents[1]
PROTOS = ["geometry.proto", "map.proto"]
TARGET = HERE / "src" / "egoslam_client" / "messages"
IMPORT = re.compile(r"^from egoslam\.v1 import (\w+) as (\w+)$", re.M)


def generate(out: pathlib.Path) -> dict:
    subprocess.run(
        ["protoc", f"-I{REPO / 'proto'}", f"--python_out={out}", f"--pyi_out={out}",
         *[str(REPO / "proto" / "egoslam" / "v1" / p) for p in PROTOS]],
        check=True,
    )
    files = {}
    for path in sorted((out / "egoslam" / "v1").iterdir()):
        text = IMPORT.sub(r"from egoslam_client.messages import \1 as \2", path.read_text())
        text = text.replace("from egoslam.v1 import", "from egoslam_client.messages import")
        files[path.name] = text
    files["__init__.py"] = (
        '"""egoslam.v1 messages, generated from proto/ by clients/python/generate_messages.py."""\n'
    )
    return files


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        files = generate(pathlib.Path(tmp))
    present = {p.name for p in TARGET.glob("*") if p.is_file()}
    if args.check:
        stale = [n for n, t in files.items()
                 if not (TARGET / n).is_file() or (TARGET / n).read_text() != t]
        extra = sorted(present - set(files))
        if stale or extra:
            print(f"stale: {stale}, not generated: {extra}; run {__file__}", file=sys.stderr)
            return 1
        return 0
    TARGET.mkdir(parents=True, exist_ok=True)
    for name in present - set(files):
        (TARGET / name).unlink()
    for name, text in files.items():
        (TARGET / name).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
