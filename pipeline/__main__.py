from pipeline.cli import entry

if __name__ == "__main__":  # spawned workers import this module too
    entry()
