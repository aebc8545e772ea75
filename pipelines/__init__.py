"""Pipeline specs (YAML), installed as the package ``phigenesis.pipelines``."""
