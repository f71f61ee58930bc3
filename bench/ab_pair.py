"""What the A/B scripts of bench/ (rays_ab.py, render_ab.py) share: two magg-host builds named
on the command line, BASE then HEAD, checked to be executables before any run."""

import argparse
import os
import sys


def parser(doc):
    """An argument parser for a script whose docstring is `doc`, with BASE and HEAD."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("base")
    ap.add_argument("head")
    return ap


def check_executables(args):
    """Exits with the reason unless both builds can be run."""
    for exe in (args.base, args.head):
        if not os.access(exe, os.X_OK):
            sys.exit(f"not an executable: {exe}")
