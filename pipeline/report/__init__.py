"""Pictures and pages made from the artifacts (figures for the report)."""
