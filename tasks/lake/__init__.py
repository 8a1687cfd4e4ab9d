"""The Parquet results lake: table schemas, atomic partition writes, SQL queries."""
