"""The aligner service: matched RGB-D pairs in, the transform between two maps out."""
