// Placeholder: replaced by the file's implementation.
