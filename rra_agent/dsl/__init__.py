"""Textual languages: UVL feature models and the RRA adaptation-rule DSL (lark grammars)."""
