"""Reading and writing: view files, the campaign, ingest of an item, zarr stores."""
