"""Builds the installable extension zip: the add-on's Python files, its manifest, the
crepuscular wheel that maturin built, and the USD step's attribute table (the export hook
authors the schema with its names; the add-on cannot import the USD package itself).

Usage: python blender_addon/build_extension.py WHEEL_DIR OUT_DIR

The manifest's `wheels = [...]` is rewritten to name the wheel found in WHEEL_DIR, so that
the zip always lists exactly the wheel it carries.
"""

from __future__ import annotations

import re
import sys
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: Files of the add-on package itself (the build script stays out of the zip).
SOURCES = sorted(p for p in HERE.glob("*.py") if p.name != "build_extension.py")
#: Files shared with the USD step, and their names in the add-on package.
SHARED = {HERE.parent / "usd" / "crepuscular_usd" / "attributes.py": "usd_attributes.py"}


def build(wheel_dir: Path, out_dir: Path) -> Path:
    wheels = sorted(wheel_dir.glob("crepuscular-*-abi3-*x86_64.whl"))
    if len(wheels) != 1:
        raise SystemExit(f"expected one linux x86_64 abi3 wheel in {wheel_dir}, found {wheels}")
    wheel = wheels[0]
    manifest = (HERE / "blender_manifest.toml").read_text()
    manifest, count = re.subn(
        r"^wheels = \[.*\]$", f'wheels = ["./wheels/{wheel.name}"]', manifest, flags=re.M
    )
    if count != 1:
        raise SystemExit("blender_manifest.toml must hold exactly one `wheels = [...]` line")
    version = re.search(r'^version = "(.+)"$', manifest, flags=re.M)
    if version is None:
        raise SystemExit("blender_manifest.toml has no version")
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"crepuscular-{version.group(1)}-linux_x64.zip"
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("blender_manifest.toml", manifest)
        for source in SOURCES:
            archive.write(source, source.name)
        for source, name in SHARED.items():
            archive.write(source, name)
        archive.write(HERE / "README.md", "README.md")
        archive.write(wheel, f"wheels/{wheel.name}")
    return target


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    print(build(Path(sys.argv[1]), Path(sys.argv[2])))
