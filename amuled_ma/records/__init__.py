"""What a job trains (`variants.Variant`) and what its ``config.json`` holds (`run_record`)."""
