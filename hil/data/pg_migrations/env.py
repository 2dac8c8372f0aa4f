"""Alembic's entry to the shared campaign store's schema: migrations run on the connection hil.data.pg_schema
hands over (never a URL of their own, so no credential passes through here), in that connection's transaction."""

from alembic import context

context.configure(
    connection=context.config.attributes["connection"],
    version_table="hil_schema_version",
    transactional_ddl=True,
)
with context.begin_transaction():
    context.run_migrations()
