"""`dofsynth assets`: pin asset folders in a manifest (`scan`) and check a recipe's assets (`check`)."""
from __future__ import annotations

import argparse
from pathlib import Path

from dofsynth.progress import say

KIND_CHOICES = ("background", "foreground")


def run_scan(args: argparse.Namespace) -> int:
    from dofsynth.assets.pins import pin_folder, write_pins

    out = Path(args.manifest)
    manifest = pin_folder(Path(args.dir), out.parent, args.kind, args.licence, progress=not args.quiet,
                          decode=not args.header, fg_dir=args.fg_dir, alpha_dir=args.alpha_dir)
    write_pins(out, manifest)
    kinds: dict[str, int] = {}
    for f in manifest["files"]:
        kinds[f["kind"]] = kinds.get(f["kind"], 0) + 1
    summary = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "no images"
    say(f"{out}: pinned {len(manifest['files'])} files ({summary}); skipped {len(manifest['skipped'])}"
          + (":" if manifest["skipped"] else ""))
    for s in manifest["skipped"]:
        say(f"  {s['path']}: {s['reason']}")
    return 0


def run_check(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from dofsynth.assets import build_library
    from dofsynth.recipe import load_recipe

    recipe = load_recipe(args.recipe)
    src = recipe.assets
    # every problem is listed, as with on_bad_asset = "skip", whatever the recipe says
    lib = build_library(replace(recipe, assets=replace(src, on_bad_asset="skip")))
    H, W = recipe.frame
    print(f"{recipe.path}: assets usable for {W}x{H} samples (assets.max_upscale = {src.max_upscale:g}, "
          f"verify = {src.verify})")
    for split in ("train", "test"):
        print(f"  {split:5s}  {len(lib.assets_for('background', split)):6d} backgrounds  "
              f"{len(lib.assets_for('foreground', split)):6d} foregrounds")
    if lib.groups:
        print(f"  near-duplicates: {len(lib.groups)} groups, each kept in one split:")
        for g in lib.groups:
            print(f"    {lib.splits[g[0]]:5s}  " + "  ".join(g))
    licences: dict[str, int] = {}
    for a in (*lib.backgrounds, *lib.foregrounds):
        licences[a.licence] = licences.get(a.licence, 0) + 1
    print("  licences (assets under each):")
    for lic, n in sorted(licences.items()):
        print(f"    {n:6d}  {lic}")
    if lib.links:
        print(f"  followed {len(lib.links)} symbolic links (files and folders under the asset folders):")
        for path, target in lib.links:
            print(f"    {path} -> {target}")
    print(f"  skipped {len(lib.skipped)} files" + (":" if lib.skipped else ""))
    for path, reason in lib.skipped:
        print(f"    {reason if reason.startswith(path) else path + ': ' + reason}")
    if lib.skipped and src.on_bad_asset == "stop":
        print(f"generate would stop at the first of them (on_bad_asset = \"stop\" in {recipe.path})")
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    args.parser.print_help()
    return 2


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "assets", help="pin asset folders in a manifest; check a recipe's assets",
        description="Work with the photos and cutouts that scenes are made from. `scan` pins a folder "
                    "(every file's sha256, size and licence) in a JSON manifest that a recipe can name "
                    "under [assets] manifest, so a later build refuses changed or missing files. "
                    "`check` builds a recipe's asset library and prints the split sizes and skipped files.")
    p.set_defaults(func=run, parser=p)
    sub = p.add_subparsers(dest="assets_command", metavar="SUBCOMMAND")

    s = sub.add_parser(
        "scan", help="write a pinning manifest of an asset folder",
        description="Scan DIR recursively (sorted; PNG, JPEG, TIFF, WebP, EXR) and write a manifest: "
                    "schema_version, root (relative to the manifest's folder) and per file its path "
                    "relative to DIR, sha256, bytes, width, height, channels, kind (background, "
                    "foreground or alpha) and licence. Licences come from a SOURCES.md table (columns "
                    "`file` and `licence`) in DIR, its parent or its subfolders, else from --licence, "
                    "else 'unknown'. Every file is decoded (--header: headers only); unreadable ones are "
                    "listed under `skipped` with their reason, never pinned.",
        epilog="Example: dofsynth assets scan my-assets --manifest data_manifest/sources/mine.json")
    s.add_argument("dir", metavar="DIR", help="the asset folder to pin")
    s.add_argument("--manifest", required=True, metavar="FILE.json", help="the pinning manifest to write")
    s.add_argument("--kind", choices=KIND_CHOICES, default=None,
                   help="the kind of every file (files under an alpha/ folder stay 'alpha'); default: "
                        "fg/ = foreground, bg/ = background, else by alpha channel")
    s.add_argument("--licence", default=None, metavar="TEXT",
                   help="licence of files that no SOURCES.md table lists (default 'unknown')")
    s.add_argument("--header", action="store_true",
                   help="read headers only (fast for huge folders; bad files are then found when loaded)")
    s.add_argument("--fg-dir", default="fg", metavar="NAME",
                   help="the paired layout's photo folder, as the recipe's assets.fg_dir (default fg)")
    s.add_argument("--alpha-dir", default="alpha", metavar="NAME",
                   help="the paired layout's matte folder, as the recipe's assets.alpha_dir (default alpha)")
    s.set_defaults(func=run_scan)

    c = sub.add_parser(
        "check", help="build a recipe's asset library and report it",
        description="Scan and check the recipe's assets as `generate` would (pins included) and print "
                    "how many backgrounds and foregrounds each split can use at the recipe's size (too small "
                    "or too magnified ones are not), the groups of near-duplicate photos (each kept in one "
                    "split), the licences, and every file that would be skipped with its reason. Exits 1 "
                    "when files would be skipped and the recipe says on_bad_asset = \"stop\".")
    c.add_argument("recipe", metavar="RECIPE.toml", help="the recipe")
    c.set_defaults(func=run_check)
