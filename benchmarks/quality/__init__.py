"""Quality scripts: the comparison tables and the no-harm check (speed lives one level up)."""
