"""What an operator watches: ``/metrics`` in the Prometheus text format (:mod:`.metrics`) and the
log as JSON lines (:mod:`.logs`). docs/operations.md, "Metrics" and "Logs", lists both."""
