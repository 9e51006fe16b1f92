"""The place database service: keyframe ingest, storage and the overlap-retrieval cascade."""
