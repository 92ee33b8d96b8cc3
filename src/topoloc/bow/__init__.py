"""Bag of visual words: tf-idf weights, inverted file, cosine similarity (Sivic & Zisserman 2003)."""

from topoloc.bow.tfidf import cosine_scores, inverse_document_frequency, inverted_file, term_counts, tfidf

__all__ = ["cosine_scores", "inverse_document_frequency", "inverted_file", "term_counts", "tfidf"]
