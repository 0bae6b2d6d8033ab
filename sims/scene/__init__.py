"""A scene: its files and parameter tables, instruments and bleed points, and the assembly that steps its models."""
