"""Print the JSON Schema of ``config.yaml`` (for editors; committed as docs/config.schema.json).

Regenerate after changing ``gateway/config.py``::

    .venv/bin/python -m gateway.config_schema > docs/config.schema.json

``tests/test_docs.py`` fails while the committed file differs from this output.
"""

from __future__ import annotations

import json
import sys


def config_schema_text() -> str:
    """The schema of ``GatewayConfig`` as stable, indented JSON (ending in a newline)."""
    from gateway.config import GatewayConfig

    schema = GatewayConfig.model_json_schema()
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}
    return json.dumps(schema, indent=2, ensure_ascii=False, sort_keys=True) + "\n"


def main() -> None:
    sys.stdout.write(config_schema_text())


if __name__ == "__main__":
    main()
