"""The foundation: input errors and validation, package data, rank-0 logging."""
