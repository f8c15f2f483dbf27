"""Typed readers and writers of the incident files, one module per file (``docs/architecture.md``).

Each module parses and checks one format and names the file and the entry in every error; the
:class:`~workbench.project.Project` knows where each file is and hands the parsed object to the stages.
"""
