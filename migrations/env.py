"""Alembic environment for bradyscope, configured from Python (see app.db.alembic_config).

- ``render_as_batch=True``: one migration history serves SQLite (which cannot
  ALTER most things in place) and PostgreSQL.
- ``compare_type=True``: ``alembic check`` also catches column type drift.
- :class:`app.models.UTCDateTime` is rendered as ``sa.DateTime(timezone=True)``
  so migrations never import application code.
- With ``config.attributes["connection"]`` set, the migration runs on that
  connection (``app.db.migrate`` holds the start-up lock on it).
"""

from __future__ import annotations

from typing import Any, Literal

import sqlalchemy as sa
from alembic import context
from sqlalchemy import engine_from_config, pool

from app.models import Base, UTCDateTime

config = context.config
target_metadata = Base.metadata


def render_item(type_: str, obj: Any, autogen_context: Any) -> str | Literal[False]:
    if type_ == "type" and isinstance(obj, UTCDateTime):
        return "sa.DateTime(timezone=True)"
    return False


def compare_type(
    context_: Any,
    inspected_column: Any,
    metadata_column: Any,
    inspected_type: Any,
    metadata_type: Any,
) -> bool | None:
    # SQLite reflects DateTime(timezone=True) as DATETIME; both are our UTCDateTime.
    if isinstance(metadata_type, UTCDateTime) and isinstance(inspected_type, sa.DateTime):
        return False
    return None  # default comparison


def _configure(**kwargs: Any) -> None:
    context.configure(
        target_metadata=target_metadata,
        render_as_batch=True,
        compare_type=compare_type,
        render_item=render_item,
        **kwargs,
    )


def run_migrations_offline() -> None:
    _configure(url=config.get_main_option("sqlalchemy.url"), literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _configure(connection=connection)
        with context.begin_transaction():
            context.run_migrations()
        return
    connectable = engine_from_config(
        config.get_section(config.config_ini_section, {}),
        prefix="sqlalchemy.",
        poolclass=pool.NullPool,
    )
    with connectable.connect() as conn:
        _configure(connection=conn)
        with context.begin_transaction():
            context.run_migrations()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
