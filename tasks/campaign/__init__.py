"""The campaign folder a lab writes: its schema, ingest into the lake, capture requests, watch and ledger."""
