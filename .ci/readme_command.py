"""Print the command of README.md's ```bash block that follows ``<!-- ci: NAME -->``.

``.ci/run`` runs the README's Quick start commands through this, so CI runs exactly what the
README tells a new user to type (tests/test_readme.py checks the blocks it names exist).
Standard library only: it runs before anything is installed.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def command(name: str, text: str | None = None) -> str:
    text = README.read_text() if text is None else text
    m = re.search(r"^<!-- ci: %s -->\n```bash\n(.*?)\n```$" % re.escape(name), text, re.S | re.M)
    if not m:
        raise SystemExit(f"README.md: no ```bash block after <!-- ci: {name} -->")
    return m.group(1)


if __name__ == "__main__":
    print(command(sys.argv[1]))
