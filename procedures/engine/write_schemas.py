"""``python -m procedures.engine.write_schemas``: regenerate the committed JSON Schemas (``procedures/schemas/``)
of the station file and of every procedure kind's file, from their pydantic models."""

from procedures.engine._loading import write_schemas

if __name__ == "__main__":
    for written_path in write_schemas():
        print(written_path)
